"""The arithmetic-hash value-noise fBm (`torchvol.noise.fast`): its hash against a uint32 reference,
its statistics against the table hash's, its lanes form (what the Dr.Jit march traces) against the
eager fbm."""

import pytest
import torch

import torchvol as tv
from torchvol.noise import fast as fastnoise
from torchvol.noise import lattice as noise


def _points(n: int, seed: int = 0, dtype=torch.float32) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=g, dtype=torch.float64) * 40.0 - 20.0).to(dtype)


def _reference_hash(x: int, y: int, z: int, seed: int) -> int:
    """`fastnoise.hash_cells` in Python uint32 arithmetic (what the int32 wrap must equal)."""
    m = 0xFFFFFFFF

    def mix(h: int) -> int:
        h ^= h >> 16
        h = (h * 0x7FEB352D) & m
        h ^= h >> 15
        h = (h * 0x1B873593) & m
        return h ^ (h >> 16)

    s = mix((seed * 0x9E3779B9 + 0x632BE5AB) & m)
    h = mix(((x * 0x1B873593) ^ (y * 0x27D4EB2F) ^ (z * 0x165667B1) ^ s) & m)
    return h >> 8


def test_hash_equals_uint32_reference():
    cells = [(0, 0, 0), (1, -1, 7), (-40000, 123456, -9), (2**31 - 1, -(2**31), 5), (17, 17, 17)]
    x, y, z = (torch.tensor(c, dtype=torch.int32) for c in zip(*cells))
    for seed in (0, 1, 123456789, 2**40 + 3):
        got = fastnoise.hash_cells(x, y, z, fastnoise._seed32(seed)).tolist()
        assert got == [_reference_hash(*c, seed) for c in cells]


def test_value_noise_at_lattice_points_is_the_hash():
    g = torch.Generator().manual_seed(1)
    cells = torch.randint(-300, 300, (500, 3), generator=g, dtype=torch.int32)
    got = fastnoise.value_noise_hashed(cells.to(torch.float32), seed=5)
    want = fastnoise.hash_cells(*cells.unbind(-1), fastnoise._seed32(5)).to(torch.float32) * 2.0**-24
    assert torch.equal(got, want)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_value_noise_range_and_statistics_match_the_table_hash(dtype):
    p = _points(200_000, dtype=dtype)
    new = fastnoise.value_noise_hashed(p, seed=3)
    old = noise.value_noise(p, seed=3)
    assert new.dtype == dtype and bool(torch.isfinite(new).all())
    assert 0.0 <= new.min() and new.max() < 1.0
    assert abs(new.mean() - old.mean()) < 0.01  # both 0.5 in expectation
    assert abs(new.std() - old.std()) < 0.01
    assert abs(fastnoise.value_noise_hashed(p, seed=4).sub(0.5).mul(new - 0.5).mean()) < 2e-3  # seeds decorrelate


def test_fbm_spectrum_matches_the_table_hash():
    """Power spectra of a 2D slice of each 4-octave fBm, in octave bands, agree within 25%."""
    n = 256
    axis = torch.arange(n, dtype=torch.float64) * (8.0 / n)
    yy, xx = torch.meshgrid(axis, axis, indexing="ij")
    p = torch.stack([xx, yy, torch.full_like(xx, 0.37)], -1).reshape(-1, 3)

    def bands(values: torch.Tensor) -> torch.Tensor:
        power = torch.fft.rfft2((values - values.mean()).reshape(n, n)).abs().square()
        ky = torch.fft.fftfreq(n).abs()[:, None] * n
        kx = torch.fft.rfftfreq(n)[None, :] * n
        k = torch.sqrt(kx**2 + ky**2)
        edges = [2, 4, 8, 16, 32, 64]  # below 2 cycles per slice: too few modes to compare
        return torch.stack([power[(k >= a) & (k < b)].mean() for a, b in zip(edges, edges[1:])])

    old, new = torch.zeros(5, dtype=torch.float64), torch.zeros(5, dtype=torch.float64)
    for seed in range(4):  # average over seeds: one field's band powers scatter by ~10-20%
        old += bands(noise.fbm(p, lambda q: noise.value_noise(q, seed=seed), octaves=4))
        new += bands(fastnoise.fbm_value_hashed(p, seed=seed, octaves=4))
    ratio = new / old
    assert bool(((ratio > 0.75) & (ratio < 1.33)).all()), ratio


def test_eager_fbm_is_noise_fbm_of_the_hashed_basis():
    p = _points(1000)
    lod = torch.arange(1000) % 6
    got = fastnoise.fbm_value_hashed(p, seed=2, octaves=5, lod=lod)
    want = noise.fbm(p, lambda q: fastnoise.value_noise_hashed(q, seed=2), octaves=5, lod=lod)
    assert torch.equal(got, want)


@pytest.mark.parametrize(("name", "kind"), [("cloud-puff", "fbm"), ("particles", "particles")])
def test_arithmetic_hash_refused_for_gradient_noise(name, kind):
    scene = tv.preset(name, width=8, height=8).model_dump()
    scene["volumes"][0]["density"][kind].update(noise="perlin", hash="arithmetic")
    with pytest.raises(ValueError, match="hash"):
        tv.render(scene)


def test_scene_with_arithmetic_hash_renders_and_differs_from_table():
    scene = tv.preset("cloud-puff", width=12, height=12).model_dump()
    table = tv.render(scene)
    scene["volumes"][0]["density"]["fbm"]["hash"] = "arithmetic"
    arith = tv.render(scene)
    assert bool(torch.isfinite(arith.radiance).all())
    assert not torch.equal(arith.radiance, table.radiance)
    assert abs(arith.alpha.mean() - table.alpha.mean()) < 0.1  # the same cloud, another draw of its noise


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_lanes_fbm_is_the_eager_fbm_bitwise(dtype):
    """`fastnoise.fbm_sum` (what the Dr.Jit march traces: every octave, LOD as a mask) on torch
    lanes against `fbm_value_hashed` (`noise.fbm`: LOD by compaction): the same values, bitwise."""
    p = _points(5000, seed=3, dtype=dtype)
    kept = 4 - torch.arange(5000) % 4  # octaves kept (`noise.fbm`'s lod), 1..4
    scales = noise.folded_scales(4, dtype=dtype, device="cpu")
    seed = int(fastnoise.mixed_seeds([11], "cpu")[0])
    for lod in (None, kept):
        eager = fastnoise.fbm_value_hashed(p, seed=11, octaves=4, lod=lod)
        lanes = fastnoise.fbm_sum(fastnoise.hashed(seed), *p.unbind(1), scales, lod, 4, 0.5)
        assert torch.equal(lanes, eager), f"LOD {'off' if lod is None else 'on'}"


@pytest.mark.parametrize("hash", ["table", "arithmetic"])
@pytest.mark.parametrize("backend", ["torch32", "torch64", "drjit"])
def test_the_planar_noise_is_the_noise_at_y_zero_bitwise(hash, backend):
    """A heightfield's value noise on the plane y = 0 (`planar_basis`: four corners, the table's
    read ahead a cell at a time, `noise.planar_corners`) against the 3-D noise at y = 0
    (`noise_basis`): bitwise, eagerly in both dtypes and in a Dr.Jit kernel, for both hashes, three
    scenes of two seeds (it fails when the plane reads other corners, another seed's table, a cell
    across the lattice's wrap, or blends them in another order)."""
    from types import SimpleNamespace

    from torchvol.fields.fbm import noise_basis, planar_basis
    from torchvol.runtime.compilation import drjit_available, traced

    if backend == "drjit" and not drjit_available():
        pytest.skip("Dr.Jit's LLVM backend is not available")
    dtype = torch.float64 if backend == "torch64" else torch.float32
    p = _points(4000, seed=5, dtype=dtype) * 700.0  # cells on both sides of the lattice's 256-cell wrap, negative too
    x, z = p[:, 0].contiguous(), p[:, 2].contiguous()
    scene, seeds = torch.arange(4000) % 3, [3, 9, 3]  # two tables, one of them twice

    def bases(to):
        return [noise_basis("value", seeds, hash, to), planar_basis(seeds, hash, to, dtype)]

    if backend == "drjit":
        import drjit as dr
        from drjit.llvm import Float, Int32

        to = SimpleNamespace(scene=scene, ints=lambda v: Int32(v.to(torch.int32).numpy()),
                             floats=lambda v: Float(v.to(torch.float32).numpy()))
        full, flat = traced(lambda lane: [b(lane(x), dr.zeros(Float, 4000), lane(z)) for b in bases(to)], x)
    else:
        to = SimpleNamespace(scene=scene, ints=lambda v: v.to(torch.int32), floats=lambda v: v.to(dtype))
        full, flat = (b(x, torch.zeros_like(x), z) for b in bases(to))
    assert torch.equal(full, flat), f"largest difference {(full - flat).abs().max():.3g} at {int((full - flat).abs().argmax())}"
    assert float(full.std()) > 0.1
    assert float(p[:, 0].abs().max()) > 256 and float(p[:, 2].min()) < 0
