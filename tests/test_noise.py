"""torchvol.noise: determinism, ranges, continuity, lattice identities, LOD, texture trick."""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchvol.noise import lattice as noise
from torchvol.noise.lattice import (
    default_noise_texture,
    fbm,
    hash3,
    hash3_columns,
    lattice_hash,
    lattice_values,
    perlin_noise,
    scene_rows,
    texture_noise,
    value_noise,
    worley_noise,
)
from torchvol.runtime.compilation import drjit_available

DTYPES = [torch.float32, torch.float64]
TEX = default_noise_texture(0)


def _tex_noise(p):
    return texture_noise(p, TEX)


NOISES = {
    "value": lambda p, seed=0: value_noise(p, seed=seed),
    "perlin": lambda p, seed=0: perlin_noise(p, seed=seed),
    "worley": lambda p, seed=0: worley_noise(p, seed=seed),
}
RANGES = {"value": (0.0, 1.0), "perlin": (-1.0, 1.0), "worley": (0.0, 1.0), "texture": (0.0, 1.0)}


def points(n, dtype, scale=10.0, seed=0):
    g = torch.Generator().manual_seed(seed)
    return ((torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * 2 * scale).to(dtype)


def test_hash3_deterministic_and_seeded():
    cells = torch.randint(-1000, 1000, (4096, 3), generator=torch.Generator().manual_seed(1))
    a, b = hash3(cells, 7), hash3(cells, 7)
    assert torch.equal(a, b)
    c = hash3(cells, 8)
    assert (a != c).float().mean() > 0.99
    assert a.min() >= 0 and a.max() < 1
    # roughly uniform, and neighbouring cells decorrelated
    assert abs(a.mean().item() - 0.5) < 0.02
    assert abs(torch.corrcoef(torch.stack([hash3(cells, 0), hash3(cells + torch.tensor([1, 0, 0]), 0)]))[0, 1]) < 0.05
    h64 = hash3(cells, 7, dtype=torch.float64)
    assert h64.dtype == torch.float64 and h64.max() < 1
    # huge / negative coordinates are fine (taken mod 2**32)
    big = torch.tensor([[2**40, -(2**35), 123], [-1, -1, -1]])
    v = hash3(big, 3)
    assert torch.isfinite(v).all() and (v >= 0).all() and (v < 1).all()


@pytest.mark.parametrize("name", sorted(NOISES))
@pytest.mark.parametrize("dtype", DTYPES)
def test_determinism_range_and_seed(name, dtype):
    fn = NOISES[name]
    p = points(2000, dtype)
    a, b = fn(p, seed=3), fn(p, seed=3)
    assert a.shape == (2000,) and a.dtype == dtype
    assert torch.equal(a, b)
    assert (fn(p, seed=4) != a).float().mean() > 0.9
    lo, hi = RANGES[name]
    assert a.min() >= lo and a.max() <= hi
    assert a.std() > 0.05  # not constant


@pytest.mark.parametrize("name", sorted(NOISES) + ["texture"])
@pytest.mark.parametrize("dtype", DTYPES)
def test_continuity(name, dtype):
    fn = _tex_noise if name == "texture" else NOISES[name]
    p = points(2000, dtype, seed=5)
    dp = torch.full_like(p, 1e-4)
    diff = (fn(p + dp) - fn(p)).abs().max().item()
    # Lipschitz-ish bound: gradients are O(1..10); the texture noise's 8-bit filter adds one
    # 1/255 step at most
    bound = 5e-3 if name != "texture" else 2.5 / 255
    assert diff < bound, f"{name}: jump {diff}"


@pytest.mark.parametrize("dtype", DTYPES)
def test_value_noise_equals_lattice_value_at_lattice_points(dtype):
    cells = torch.randint(-50, 50, (500, 3), generator=torch.Generator().manual_seed(2))
    v = value_noise(cells.to(dtype), seed=9)
    assert torch.equal(v, lattice_values(cells, 9, dtype)[:, 0])


@pytest.mark.skipif(not drjit_available(), reason="needs Dr.Jit's LLVM backend")
@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**64 - 1), shift=st.integers(0, 40))
def test_hash3_in_a_kernel_is_the_eager_hash(seed, shift):
    """The kernel's hash (the march dither's) gives eager's float32 bits for cells of any size and
    sign, int64 and int32 (taken mod 2**32 alike), and keeps their shape."""
    g = torch.Generator().manual_seed(seed % 2**63)
    cells = torch.randint(-(2**shift) - 5, 2**shift + 5, (2, 513, 3), generator=g)
    for c in (cells, cells.to(torch.int32), cells[:, :0]):  # none: an empty chunk
        eager, kernel = hash3(c, seed, dtype=torch.float32), hash3(c, seed, dtype=torch.float32, kernel=True)
        diff = (eager != kernel).nonzero()
        assert kernel.shape == eager.shape and not len(diff), f"{len(diff)} values differ, first at {diff[:1].tolist()}"
        x, y, z = c.reshape(-1, 3).unbind(1)  # strided columns, as the dither's keys are
        columns = hash3_columns(x, y, z, seed, dtype=torch.float32, kernel=True)
        assert torch.equal(columns, eager.reshape(-1)), "hash3_columns differs from hash3 of the stacked cells"


def test_lattice_hash_is_a_period_256_permutation_chain():
    cells = torch.randint(-1000, 1000, (2000, 3), generator=torch.Generator().manual_seed(4))
    h = lattice_hash(cells, 5)
    assert torch.equal(h, lattice_hash(cells + 256 * torch.tensor([1, -2, 3]), 5))
    assert h.min() >= 0 and h.max() < 256 and len(h.unique()) > 200
    assert not torch.equal(h, lattice_hash(cells, 6))


@pytest.mark.parametrize("period", [None, 5, 300])
@pytest.mark.parametrize("offsets", [(0, 1), (-1, 0, 1)])
def test_the_shared_chain_is_lattice_hash_of_each_cell(offsets, period):
    """`_lattice_chain` over `_cells` (a cell's 8 corners, the 27 cells around): each hash is
    `lattice_hash` of its cell, wrapped by the period first, in x-fastest order; with tables
    composed with the permutation (`chained_values`) as its last gather, their rows at that hash."""
    cells = torch.randint(-1000, 1000, (500, 3), generator=torch.Generator().manual_seed(3))
    perm, columns = noise.scene_lattice_tables((7,), "cpu")
    lattice = noise._cells(cells.double().unbind(1), offsets, period=period)
    hashes = noise._lattice_chain(perm, *lattice)
    composed = noise._lattice_chain(perm, *lattice, last=[noise.chained_values(perm, c) for c in columns])
    first = noise._lattice_chain(perm, *lattice, last=noise.chained_values(perm, columns[0]))
    neighbours = [(dx, dy, dz) for dz in offsets for dy in offsets for dx in offsets]
    assert offsets != (0, 1) or neighbours == noise._CORNERS
    for off, h, values, value in zip(neighbours, hashes, composed, first, strict=True):
        c = cells + torch.tensor(off)
        assert torch.equal(h.long(), lattice_hash(c if period is None else torch.remainder(c, period), 7)), off
        assert all(torch.equal(v, col[h.long()]) for v, col in zip(values, columns, strict=True)), off
        assert torch.equal(value, columns[0][h.long()]), off


def test_perlin_zero_at_lattice_points():
    cells = torch.randint(-50, 50, (500, 3), generator=torch.Generator().manual_seed(2)).double()
    assert perlin_noise(cells).abs().max() == 0


def test_worley_zero_at_feature_point():
    cell = torch.tensor([[3, -4, 5]])
    feat = lattice_values(cell, 11, torch.float64)
    assert worley_noise(cell.double() + feat, seed=11).item() < 1e-12


# Ken Perlin's 12 edge gradients, indexed by the corner's hash mod 12
GRADS = torch.tensor([(1, 1, 0), (-1, 1, 0), (1, -1, 0), (-1, -1, 0), (1, 0, 1), (-1, 0, 1), (1, 0, -1), (-1, 0, -1),
                      (0, 1, 1), (0, -1, 1), (0, 1, -1), (0, -1, -1)], dtype=torch.float64)


def _wrapped(cells, period):
    return cells if period is None else torch.remainder(cells, period)


def _perlin_reference(p, seed, period=None):
    """Gradient noise from its definition, in float64 [N]: each corner's gradient GRADS[lattice_hash
    mod 12] dotted with the offset from the corner, weighted by the product of the quintic fades."""
    p = p.double()
    cell, f = torch.floor(p).long(), p - torch.floor(p)
    corners = torch.tensor(noise._CORNERS)  # [8, 3]
    h = lattice_hash(_wrapped(cell[:, None] + corners, period), seed)  # [N, 8]
    dots = (GRADS[h % 12] * (f[:, None] - corners)).sum(-1)
    u = (f * f * f * (f * (f * 6 - 15) + 10))[:, None]  # [N, 1, 3]
    weights = torch.where(corners.bool(), u, 1 - u).prod(-1)  # [N, 8]
    return (weights * dots).sum(-1)


def _worley_reference(p, seed, period=None):
    """F1 from its definition, in float64 [N]: the nearest of the 27 cells' feature points
    cell + lattice_values(cell), clamped to 1."""
    p = p.double()
    cell, best = torch.floor(p).long(), torch.full(p.shape[:1], float("inf"), dtype=torch.float64)
    for dz in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                c = cell + torch.tensor([dx, dy, dz])
                best = torch.minimum(best, (c + lattice_values(_wrapped(c, period), seed, torch.float64) - p).square().sum(-1))
    return best.sqrt().clamp_max(1.0)


def _lattice_test_points(n, dtype, seed):
    """[n + 300, 3] points across 600 cells, negative coordinates included, and 300 lattice points."""
    g = torch.Generator().manual_seed(seed)
    cells = torch.randint(-300, 300, (300, 3), generator=g)
    return torch.cat([points(n, dtype, scale=300.0, seed=seed), cells.to(dtype)])


REFERENCES = {"perlin": _perlin_reference, "worley": _worley_reference}


@pytest.mark.parametrize("period", [None, 6])
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("name", sorted(REFERENCES))
def test_gradient_and_worley_noise_follow_their_definition(name, dtype, period):
    """The lanes noise (what eager and the Dr.Jit march run) against an independent float64 oracle
    over `lattice_hash` / `lattice_values`: the seed's tables, whole cells, the period."""
    fn = {"perlin": perlin_noise, "worley": worley_noise}[name]
    tol = 1e-12 if dtype == torch.float64 else 2e-6
    for seed in (0, 5, 2**40 + 3):
        p = _lattice_test_points(3000, dtype, seed)
        err = (fn(p, seed=seed, period=period).double() - REFERENCES[name](p, seed, period)).abs()
        assert float(err.max()) <= tol, f"seed {seed}: off by {float(err.max()):.3g} at {p[int(err.argmax())].tolist()}"


def test_the_gradient_rule_is_perlins_table():
    """`_gradient_dot`'s selects give GRADS[h mod 12] · d for every hash of three stacked blocks."""
    h = torch.arange(3 * 512, dtype=torch.int32)
    d = torch.randn(3, h.shape[0], generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    assert torch.equal(noise._gradient_dot(h, *d), (GRADS[(h.long() & 255) % 12] * d.T).sum(-1))


SCENE_NOISES = {"value": (value_noise, noise.value_noise_scenes), "perlin": (perlin_noise, noise.perlin_noise_scenes),
                "worley": (worley_noise, noise.worley_noise_scenes)}


@pytest.mark.parametrize("dtype", DTYPES)
def test_fbm_lod_equals_fewer_octaves(dtype):
    p = points(3000, dtype, scale=5.0, seed=3)
    lod = torch.randint(0, 7, (3000,), generator=torch.Generator().manual_seed(4))
    got = fbm(p, _tex_noise, lod=lod)
    for L in range(0, 7):
        m = lod == L
        octaves = min(max(L, 1), 5)
        want = fbm(p[m], _tex_noise, octaves=octaves)
        assert torch.equal(got[m], want), f"lod {L}"


@pytest.mark.parametrize("name", sorted(SCENE_NOISES))
@pytest.mark.parametrize("dtype", DTYPES)
def test_noise_of_several_scenes_is_bitwise_each_scenes_own(dtype, name):
    """One pass over every scene's points (stacked tables), and the same through fbm's compaction."""
    one, scenes = SCENE_NOISES[name]
    n, seeds = 4000, [7, 0, 2**40 + 3, 7]
    p = points(n, dtype, scale=300.0, seed=8)  # past the 256-cell period, negative cells included
    g = torch.Generator().manual_seed(9)
    scene, lod = torch.randint(0, len(seeds), (n,), generator=g), torch.randint(1, 6, (n,), generator=g)
    got = scenes(p, scene_rows(scene), seeds)
    got_fbm = fbm(p, lambda q, rows: scenes(q, rows, seeds), lod=lod, rows=scene_rows(scene))
    for b, seed in enumerate(seeds):
        m = scene == b
        assert torch.equal(got[m], one(p[m], seed=seed)), f"scene {b}"
        assert torch.equal(got_fbm[m], fbm(p[m], lambda q: one(q, seed=seed), lod=lod[m])), f"fbm, scene {b}"


@pytest.mark.skipif(not drjit_available(), reason="Dr.Jit's LLVM backend is not available")
@pytest.mark.parametrize(("name", "period"), [("value", None), ("perlin", None), ("perlin", 5), ("worley", None),
                                            ("worley", 5)])
def test_the_lanes_noise_traced_by_drjit_is_the_eager_noise(name, period):
    """The lattice noises as the Dr.Jit march traces them (`value_lanes`, `perlin_lanes`,
    `worley_lanes` on Dr.Jit arrays, several scenes' tables stacked) against the eager noise of
    each point's own seed: bitwise, but for Worley's square root (Dr.Jit's, within an ulp)."""
    from drjit.llvm import Float, Int32

    seeds = (7, 0, 2**40 + 3)
    p = _lattice_test_points(20000, torch.float32, seed=2)
    scene = torch.randint(0, len(seeds), (p.shape[0],), generator=torch.Generator().manual_seed(4))
    table, columns = noise.scene_lattice_tables(seeds, "cpu")
    xyz, perm, rows = [Float(c.numpy()) for c in p.unbind(1)], Int32(table.numpy()), Int32(scene_rows(scene).numpy())
    values = [Float(noise.chained_values(table, c).float().numpy()) for c in columns]
    kw = {} if period is None else {"period": period}
    got = torch.from_numpy(np.array({"value": lambda: noise.value_lanes(*xyz, perm, values[0], rows),
                                     "perlin": lambda: noise.perlin_lanes(*xyz, perm, rows, **kw),
                                     "worley": lambda: noise.worley_lanes(*xyz, perm, values, rows, **kw)}[name]()))
    one = SCENE_NOISES[name][0]
    eager = torch.empty_like(got)
    for b, seed in enumerate(seeds):
        m = scene == b
        eager[m] = one(p[m], seed=seed, **kw)
    if name == "worley":
        torch.testing.assert_close(got, eager, rtol=0.0, atol=1.2e-7)
    else:
        assert torch.equal(got, eager), f"largest difference {float((got - eager).abs().max())}"


def test_fbm_compaction_evaluates_only_needed_points():
    p = points(1000, torch.float32, seed=6)
    lod = torch.where(torch.arange(1000) < 100, 5, 1)
    counts = []

    def counting(q):
        counts.append(q.shape[0])
        return _tex_noise(q)

    fbm(p, counting, lod=lod)
    assert counts == [1000, 100, 100, 100, 100]
    counts.clear()
    fbm(p, counting, lod=torch.ones(1000, dtype=torch.long))
    assert counts == [1000]


def test_fbm_weights_and_lacunarity():
    p = points(500, torch.float64, seed=7)
    f = fbm(p, value_noise, octaves=3, lacunarity=2.0, fold="sequential")
    want = 0.5 * value_noise(p) + 0.25 * value_noise(p * 2) + 0.125 * value_noise(p * 4)
    assert torch.allclose(f, want, atol=1e-14)
    # folded constants (the Mesa model) and the sequential product agree up to rounding
    a = fbm(p, value_noise, octaves=7)
    b = fbm(p, value_noise, octaves=7, fold="sequential")
    assert torch.allclose(a, b, atol=1e-9)
    g = fbm(p, value_noise, octaves=2, gain=0.6)
    assert torch.allclose(g, 0.5 * value_noise(p) + 0.3 * value_noise(p * 2.02), atol=1e-14)


def test_default_texture_green_is_shifted_red():
    tex = default_noise_texture(5)
    assert tex.shape == (256, 256, 4) and tex.dtype == torch.uint8
    assert torch.equal(tex, default_noise_texture(5))
    assert not torch.equal(tex, default_noise_texture(6))
    r, g = tex[..., 0].long(), tex[..., 1].long()
    y, x = torch.meshgrid(torch.arange(256), torch.arange(256), indexing="ij")
    assert torch.equal(g, r[(y - 239) % 256, (x - 37) % 256])
    for c in (0, 2, 3):  # random channels use the whole byte range
        assert tex[..., c].min() < 5 and tex[..., c].max() > 250


@pytest.mark.parametrize("filter_bits", [8, None])
@pytest.mark.parametrize("dtype", DTYPES)
def test_texture_noise_continuous_across_integer_z(dtype, filter_bits):
    """The (37, 239) / .yx trick: the value at z = k equals the limit from below (z -> k-)."""
    g = torch.Generator().manual_seed(8)
    xy = (torch.rand(2000, 2, generator=g, dtype=torch.float64) * 40 - 20).to(dtype)
    k = torch.randint(-20, 20, (2000, 1), generator=g).to(dtype)
    eps = 1e-9 if dtype == torch.float64 else 1e-4
    n_at = texture_noise(torch.cat([xy, k], 1), TEX, filter_bits=filter_bits)
    n_below = texture_noise(torch.cat([xy, k - eps], 1), TEX, filter_bits=filter_bits)
    # both sides sample the same texels with the same filter weights; f.z -> 1 differs, and in
    # float32 uv = p.xy + (37, 239) p.z + f rounds at a different magnitude (ulp of ~5000: 5e-4)
    tol = 1e-7 if dtype == torch.float64 else 1e-3
    assert (n_at - n_below).abs().max() < tol
    # whereas a jump in z of the same size inside a cell is also tiny, crossing without the
    # G/R relation would jump by O(1): check the relation matters
    bad = TEX.clone()
    bad[..., 1] = torch.flip(bad[..., 1], dims=[0])
    jump = texture_noise(torch.cat([xy, k], 1), bad, filter_bits=filter_bits)
    jump = jump - texture_noise(torch.cat([xy, k - eps], 1), bad, filter_bits=filter_bits)
    assert jump.abs().max() > 0.3
    assert n_at.dtype == dtype and n_at.min() >= 0 and n_at.max() <= 1


def test_texture_noise_exact_lattice_values():
    """At integer points the noise is the G texel at (x + 37 z, y + 239 z)."""
    cells = torch.randint(-300, 300, (500, 3), generator=torch.Generator().manual_seed(9))
    n = texture_noise(cells.float(), TEX)
    u = (cells[:, 0] + 37 * cells[:, 2]) % 256
    v = (cells[:, 1] + 239 * cells[:, 2]) % 256
    want = TEX[v, u, 1].float() * torch.tensor(1 / 255, dtype=torch.float32)
    assert torch.equal(n, want)


def test_texture_noise_bad_texture():
    with pytest.raises(ValueError, match="texture"):
        texture_noise(torch.zeros(3, 3), torch.zeros(128, 128, 4, dtype=torch.uint8))


@settings(max_examples=20, deadline=None)
@given(
    scale=st.floats(min_value=-1e6, max_value=1e6, allow_nan=False),
    freq=st.floats(min_value=1e-3, max_value=1e4),
    dt=st.sampled_from(DTYPES),
    seed=st.integers(min_value=-(2**40), max_value=2**40),
)
def test_extreme_coordinates_finite_and_in_range(scale, freq, dt, seed):
    base = torch.tensor([[1.0, -0.7, 0.3], [0.0, 0.0, 0.0], [-1.0, 1.0, 1.0], [0.5, 0.25, -0.125]])
    p = (base * scale).to(dt) * freq
    for name in NOISES:
        v = NOISES[name](p, seed=seed)
        lo, hi = RANGES[name]
        assert torch.isfinite(v).all() and (v >= lo).all() and (v <= hi).all(), name
    v = texture_noise(p, TEX)
    assert torch.isfinite(v).all() and (v >= 0).all() and (v <= 1).all()
    f = fbm(p, lambda q: texture_noise(q, TEX) * 2 - 1)
    assert torch.isfinite(f).all() and (f.abs() <= 1).all()


def _stacked_tables(seeds):
    tables = [noise.texture_table(noise.default_noise_texture(s)) for s in seeds]
    return tables, noise.packed_table(torch.cat(tables))


def _hard_points(dtype):
    """[80,004, 3] points from |p| ≤ 2 to 5·10⁷, past the float->int32 overflow, and NaN."""
    g = torch.Generator().manual_seed(1)
    return torch.cat([(torch.rand(20000, 3, generator=g, dtype=dtype) - 0.5) * scale for scale in (4.0, 400.0, 1e5, 1e8)]
                     + [torch.tensor([[float("nan"), 0, 0], [1e30, 1, 2], [-1e30, 1, 2], [0.5, 0.5, 1e7]], dtype=dtype)])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_integer_texture_noise_is_the_float64_one_bitwise(dtype):
    """`noise.texture_noise_coords` (int32/int64 steps, stacked tables: the template's eager noise
    and what its Dr.Jit march traces) against `noise.texture_noise_reference` (float64 steps): every
    value equal, also past the float->int32 overflow and at NaN."""
    tables, packed = _stacked_tables([0, 5])
    p = _hard_points(dtype)
    s = torch.arange(p.shape[0]) % 2
    expected = torch.where(s == 0, noise.texture_noise_reference(p, tables[0]), noise.texture_noise_reference(p, tables[1]))
    got = noise.texture_noise_coords(*p.unbind(1), packed, s * 65536)
    same = (got == expected) | (got.isnan() & expected.isnan())
    assert same.all(), f"{int((~same).sum())} of {len(p)} differ, first at {p[~same][0].tolist()}"


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-3e9, 3e9, allow_nan=False, width=32), min_size=3, max_size=3))
def test_integer_texture_noise_is_bitwise_at_any_float32_point(xyz):
    tables, packed = _stacked_tables([3])
    p = torch.tensor([xyz], dtype=torch.float32)
    assert torch.equal(noise.texture_noise_coords(*p.unbind(1), packed), noise.texture_noise_reference(p, tables[0]))
