"""`torchvol.ops.lanes`: each function gives the same values on torch tensors and on Dr.Jit arrays
(bitwise where both backends compute the same IEEE operation; `expm1`, which Dr.Jit lacks, within
a few ulps of float64), and keeps a Python number's precision in a float64 render."""

import numpy as np
import pytest
import torch

from torchvol.ops import lanes
from torchvol.runtime.compilation import drjit_available

pytestmark = pytest.mark.skipif(not drjit_available(), reason="Dr.Jit's LLVM backend is not available")


def _points(n: int = 4096, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = (torch.rand(n, generator=g) - 0.5) * 40.0
    x[:8] = torch.tensor([0.0, -0.0, 0.5, -0.5, 1.5, 2.5, 1e-30, -3e9])  # ties, signed zeros, tiny, huge
    return x


def _jit(t: torch.Tensor):
    from drjit.llvm import Float, Int32

    return (Int32 if t.dtype == torch.int32 else Float)(t.numpy())


def _back(v) -> torch.Tensor:
    return torch.from_numpy(np.array(v))


@pytest.mark.parametrize("name", ["exp", "log", "log2", "sqrt", "floor", "abs", "round", "smoothstep01"])
def test_unary_functions_agree_bitwise(name):
    x = _points()
    if name in ("log", "log2", "sqrt"):
        x = x.abs() + 1e-3
    fn = getattr(lanes, name)
    torch_values, jit_values = fn(x), _back(fn(_jit(x)))
    if name in ("exp", "log", "log2", "sqrt"):  # each backend's own (Dr.Jit's sqrt too): within an ulp or two
        torch.testing.assert_close(jit_values, torch_values, rtol=4e-7, atol=0.0)
    else:
        assert torch.equal(jit_values, torch_values), f"{name}: largest difference {float((jit_values - torch_values).abs().max())}"


def test_sqrt_rounded_is_correctly_rounded_in_both():
    """`sqrt_rounded`: numpy's float32 sqrt (IEEE, correctly rounded) on both backends, bitwise,
    over 24 binades (torch's own float32 sqrt is an ulp off for ~17% of these on this build)."""
    g = torch.Generator().manual_seed(3)
    x = torch.exp(torch.empty(200_000).uniform_(-8.0, 8.0, generator=g))
    x[:4] = torch.tensor([0.0, 1.0, 4.0, 2.0])
    exact = torch.from_numpy(np.sqrt(x.numpy()))
    for name, values in (("torch", lanes.sqrt_rounded(x)), ("Dr.Jit", _back(lanes.sqrt_rounded(_jit(x))))):
        bad = (values != exact).nonzero()
        assert not len(bad), f"{name}: {len(bad)} of {len(x)} not correctly rounded, first x = {x[bad[0]].item()!r}"


def test_expm1_is_accurate_near_zero_in_both():
    x = torch.cat([torch.logspace(-30, 1, 400), -torch.logspace(-30, 1, 400), torch.tensor([0.0])])
    exact = torch.expm1(x.double())
    for values in (lanes.expm1(x), _back(lanes.expm1(_jit(x)))):
        rel = ((values.double() - exact).abs() / exact.abs().clamp_min(1e-300)).max()
        assert float(rel) < 4e-7, float(rel)


def test_atan_and_tan_are_accurate_in_both():
    """Dr.Jit's atan does not compile under LLVM 15: the lanes' own (Cephes' atanf), within 2e-7
    of float64 over huge, tiny, infinite and signed arguments; tan is each backend's."""
    x = torch.cat([_points(), torch.tensor([float("inf"), -float("inf"), 1e30, -1e30])])
    exact = torch.atan(x.double())
    for values in (lanes.atan(x), _back(lanes.atan(_jit(x)))):
        gap = float((values.double() - exact).abs().max())
        assert gap < 2e-7, f"atan off by {gap:.3g}"
    angle = x[:4096].clamp(-1.5, 1.5)
    torch.testing.assert_close(_back(lanes.tan(_jit(angle))), lanes.tan(angle), rtol=4e-6, atol=1e-6)


def test_lerp_where_minimum_clamp_and_gather_agree_bitwise():
    a, b, w = _points(seed=1), _points(seed=2), torch.rand(4096, generator=torch.Generator().manual_seed(3)) * 1.4 - 0.2
    assert torch.equal(_back(lanes.lerp(_jit(a), _jit(b), _jit(w))), lanes.lerp(a, b, w))
    assert torch.equal(lanes.lerp(a, b, w), torch.lerp(a, b, w))
    assert torch.equal(_back(lanes.where(_jit(a) > 0.0, _jit(a), 0.0)), lanes.where(a > 0.0, a, 0.0))
    assert torch.equal(_back(lanes.minimum(_jit(a), _jit(b))), lanes.minimum(a, b))
    assert torch.equal(_back(lanes.maximum(_jit(a), 1.0)), lanes.maximum(a, 1.0))
    assert torch.equal(_back(lanes.clamp(_jit(a), -1.0, 2.0)), lanes.clamp(a, -1.0, 2.0))
    table, index = _points(seed=4), (torch.arange(4096, dtype=torch.int32) * 7) % 4096
    assert torch.equal(_back(lanes.gather(_jit(table), _jit(index))), lanes.gather(table, index))


def test_remainder_is_floor_modulo_in_both():
    i = torch.arange(-1000, 1000, dtype=torch.int32) * 7919
    for n in (1, 5, 12, 256, 300):
        want = torch.remainder(i, n)
        assert torch.equal(lanes.remainder(i, n), want) and torch.equal(_back(lanes.remainder(_jit(i), n)), want), n
    assert int(lanes.remainder(i, 5).min()) == 0


def test_a_python_number_keeps_its_precision_in_float64():
    x = torch.zeros(3, dtype=torch.float64)
    third = 1.0 / 3.0
    assert float(lanes.maximum(x, third)[0]) == third and float(lanes.minimum(third, x + 1.0)[0]) == third
    assert lanes.maximum(x, third).dtype == torch.float64


def test_clamp_passes_nan_through_in_both():
    x = torch.tensor([float("nan"), -5.0, 5.0, 0.5])
    assert torch.equal(_back(lanes.clamp(_jit(x), 0.0, 1.0)).isnan(), lanes.clamp(x, 0.0, 1.0).isnan())


def test_row_lanes_are_the_selected_rows():
    """`row_lanes(idx)`: rows gathered in the kernel from a tensor as it lies are the columns of
    its index_select, bitwise, for [R] and [R, C] tensors, repeated and unordered rows."""
    g = torch.Generator().manual_seed(5)
    idx = torch.tensor([7, 0, 3, 3, 11, 2])
    row = lanes.row_lanes(idx)
    for x in (torch.randn(12, generator=g), torch.randn(12, 3, generator=g), torch.randn(12, 3, generator=g)[:, 1:]):
        got = row(x)
        want = lanes.columns(x.index_select(0, idx))
        pairs = [(got, want)] if x.ndim == 1 else list(zip(got, want, strict=True))
        for k, (a, b) in enumerate(pairs):
            assert torch.equal(_back(a), b), f"column {k} of a {tuple(x.shape)} tensor: {_back(a).tolist()} vs {b.tolist()}"


def test_gather_pair_reads_both_values_of_a_pair_bitwise():
    """`gather_pair` on a `pairs_of` table in a kernel (one 64-bit word a pair) gives the two
    columns torch's index_select gives, bitwise: signed zeros, infinities, denormals and a NaN's
    payload included (a word split at the wrong half or sign-extended would not)."""
    table = torch.tensor([[1.5, -0.0], [float("inf"), -3e-45], [float("-inf"), 7.0], [2.0**-149, -2.5]])
    table = torch.cat([table, torch.tensor([[0.0, 0.0]]).view(torch.int32).add(0x7FC00123).view(torch.float32)])
    idx = torch.tensor([4, 0, 3, 3, 1, 2], dtype=torch.int32)
    eager = lanes.gather_pair(table, idx)
    kernel = lanes.gather_pair(lanes.pairs_of(table), _jit(idx))
    for k in range(2):
        got, want = _back(kernel[k]).view(torch.int32), eager[k].contiguous().view(torch.int32)
        assert torch.equal(got, want), f"value {k} of each pair: bits {got.tolist()} vs {want.tolist()}"


@pytest.mark.parametrize("channels", [1, 3, 5])
def test_interleaved_rows_are_the_columns_stacked(channels):
    """`interleaved` lanes, evaluated by the kernel that computes them (here a product), read back
    by `rows_of` as the tensor [n, C] torch.stack of the columns gives, bitwise."""
    import drjit as dr

    cols = [_points(seed=c) for c in range(channels)]
    computed = [_jit(c) * 1.5 for c in cols]  # lazy: the ravel is written by the kernel that computes them
    flat = lanes.interleaved(computed)
    dr.eval(flat)
    got = lanes.rows_of(flat, channels)
    expected = torch.stack([c * 1.5 for c in cols], dim=1)
    assert got.shape == (cols[0].shape[0], channels)
    assert torch.equal(got, expected), f"largest difference {float((got - expected).abs().max()):.3g}"
