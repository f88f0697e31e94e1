"""The Dr.Jit DDA walk (`torchvol.voxel.walk.drjit_traverse`) against the plain one (`dda.traverse`,
`dda.hybrid_traverse`): the same hits, bitwise; voxel renders by default bitwise the eager reference
(a fog's light within float rounding)."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import torchvol as tv
from torchvol.ops.grid_ops import chebyshev_distance
from torchvol.runtime.compilation import drjit_available
from torchvol.voxel import walk
from torchvol.voxel.dda import hybrid_traverse, traverse
from torchvol.voxel.passes.fog import FogGlowRays

FIELDS = ("hit", "cell", "axis", "t", "material", "steps", "t_exit")


def _world(seed: int, n: int, dtype, *, scenes=2, shape=(6, 7, 8), p=0.12):
    """Random material grids of `scenes` scenes (each its own cell range) and n rays of random
    scenes, some axis-parallel, from inside and outside: (rays, lookup, table arguments, ranges,
    (distance lookup, distance table), (the rays' scenes, each scene's flat base, lo and hi))."""
    g = torch.Generator().manual_seed(seed)
    occ = (torch.rand((scenes,) + shape, generator=g) < p) * torch.randint(1, 6, (scenes,) + shape, generator=g)
    occ = occ.to(torch.uint8)
    lo = torch.randint(-5, 5, (scenes, 3), generator=g)
    hi = lo + torch.tensor([shape[2], shape[1], shape[0]])
    s = torch.randint(0, scenes, (n,), generator=g)
    span = (hi - lo)[s].to(dtype)
    o = lo[s] + (torch.rand(n, 3, generator=g, dtype=dtype) * 3 - 1) * span
    d = lo[s] + torch.rand(n, 3, generator=g, dtype=dtype) * span - o
    k = n // 8
    d[:k, 1:], d[k:2 * k, ::2], d[2 * k:3 * k, 2] = 0, 0, 0  # axis-parallel and axis-plane rays
    d = d / d.norm(dim=1, keepdim=True).clamp_min(1e-12)
    d[d.norm(dim=1) == 0] = torch.tensor([1.0, 0.0, 0.0], dtype=dtype)
    Z, Y, X = shape

    def lookup(c, ids):
        sc = s[ids]
        r = c - lo[sc]
        return occ.reshape(-1)[((sc * Z + r[:, 2]) * Y + r[:, 1]) * X + r[:, 0]].long()

    base = ((s * Z - lo[s, 2]) * Y - lo[s, 1]) * X - lo[s, 0]
    field = torch.stack([chebyshev_distance(g > 0) for g in occ])

    def distance(c, ids):
        sc = s[ids]
        r = c - lo[sc]
        return field.reshape(-1)[((sc * Z + r[:, 2]) * Y + r[:, 1]) * X + r[:, 0]].long()

    per_scene = (s, ((torch.arange(scenes) * Z - lo[:, 2]) * Y - lo[:, 1]) * X - lo[:, 0], lo, hi)
    return (o, d), lookup, (occ.reshape(-1), base, torch.tensor([Y, X])), (lo[s], hi[s]), (distance, field.reshape(-1)), per_scene


VOXEL_PRESETS = [name for name in tv.preset_names() if name.startswith("voxel-")]
needs_drjit = pytest.mark.skipif(not drjit_available(), reason="Dr.Jit's LLVM backend is not available")


def _assert_same_walk(seed, n, *, max_steps, limited, late, hybrid):
    """`walk.drjit_traverse` against `traverse` or, `hybrid`, `hybrid_traverse` (on larger,
    sparser grids, where rays jump), float32."""
    shape, p = ((14, 12, 16), 0.03) if hybrid else ((6, 7, 8), 0.12)
    (o, d), lookup, table, (lo, hi), (distance, field), (s, base, lo_s, hi_s) = _world(seed, n, torch.float32, shape=shape, p=p)
    g = torch.Generator().manual_seed(seed)
    t_max = torch.rand(n, generator=g) * 12 if limited else None
    t_min = torch.rand(n, generator=g) * 6 if late else None  # rays that start part-way
    if hybrid:
        plain = hybrid_traverse(o, d, lookup, distance, lo, hi, max_steps=max_steps, t_min=t_min, t_max=t_max)
    else:
        plain = traverse(o, d, lookup, lo, hi, max_steps=max_steps, t_min=t_min, t_max=t_max)
    kernel = walk.drjit_traverse(o, d, *table, lo, hi, max_steps=max_steps, t_min=t_min, t_max=t_max,
                                 distance=field if hybrid else None)
    # each ray's range and base gathered from its scene's inside the kernel (the tracer's way)
    by_scene = walk.drjit_traverse(o, d, table[0], base, table[2], lo_s, hi_s, max_steps=max_steps, t_min=t_min,
                                   t_max=t_max, distance=field if hybrid else None, scene=s)
    for name in FIELDS:
        for other in (kernel, by_scene):
            a, b = getattr(plain, name), getattr(other, name)
            assert a.dtype == b.dtype and torch.equal(a, b), \
                f"{name}: {int((a != b).sum())} of {n} rays differ (first at ray {int((a != b).nonzero()[0, 0])})"
    return plain


@needs_drjit
@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 200), max_steps=st.integers(1, 60), limited=st.booleans(),
       late=st.booleans(), hybrid=st.booleans())
def test_the_drjit_walk_is_bitwise_the_plain_walk(seed, n, max_steps, limited, late, hybrid):
    """`walk.drjit_traverse`: `walk_step` (lanes) in one Dr.Jit loop per ray; axis-parallel rays
    and rays that start inside or part-way included."""
    _assert_same_walk(seed, n, max_steps=max_steps, limited=limited, late=late, hybrid=hybrid)


@needs_drjit
def test_the_drjit_walk_jumps_and_the_comparison_sees_a_wrong_walk(monkeypatch):
    """The hybrid walk's rays jump (fewer steps than the plain walk's), and a walk that keeps its
    rays one step too long is caught (the test above can fail)."""
    h = _assert_same_walk(6, 1500, max_steps=80, limited=False, late=False, hybrid=True)
    assert h.hit.any() and (~h.hit).any()
    (o, d), lookup, _, (lo, hi), _, _ = _world(6, 1500, torch.float32, shape=(14, 12, 16), p=0.03)
    assert h.steps.sum() < 0.8 * traverse(o, d, lookup, lo, hi, max_steps=80).steps.sum(), "the rays did not jump"
    step = walk.walk_step

    def one_too_many(state, r, g):
        from types import SimpleNamespace

        return step(state, r, SimpleNamespace(**{**vars(g), "max_steps": g.max_steps + 1}))

    monkeypatch.setattr(walk, "walk_step", one_too_many)
    with pytest.raises(AssertionError, match="differ"):
        _assert_same_walk(5, 300, max_steps=6, limited=False, late=False, hybrid=False)


@pytest.mark.parametrize("name, overrides", [(name, {}) for name in VOXEL_PRESETS]
                         + [("voxel-fog", {"voxels.traversal": "hybrid"}), ("voxel-glow", {"voxels.traversal": "hybrid"}),
                            ("voxel-glow", {"voxels.fog": {"density": 0.08, "scale_height": 3.0}})])
def test_default_renders_are_eager_renders(name, overrides, monkeypatch):
    """Every walk gives the eager walk's bits: the default (Dr.Jit's walk, the glow's and the fog's
    sums inside it: the eager per-cell callback never runs) renders every output bitwise as the
    eager reference does (a fog's light, the neighbour AO and the cones excepted, whose exp and log
    are Dr.Jit's in the kernels, the GI paths, whose directions' sin, cos and sqrt are, and the
    rounded voxels, whose sqrt is correctly rounded in Dr.Jit and not in torch: within float
    rounding); with fog or glow a hybrid scene walks plainly on every path."""
    scene = tv.load_scene(tv.preset(name, width=40, height=30), overrides=overrides)
    slow = tv.render(scene, compile="off")
    if drjit_available():
        def no_callback(self, *args):
            raise AssertionError("the Dr.Jit walk called the eager per-cell callback")

        monkeypatch.setattr(FogGlowRays, "_visit", no_callback)
    fast = tv.render(scene)
    assert slow.stats["plan"]["walk"] == "eager" and fast.stats["plan"]["walk"] == ("drjit" if drjit_available() else "eager")
    fog = scene.voxels.fog is not None
    cones = scene.voxels.gi is not None and scene.voxels.gi.method == "cone"
    rounded = scene.voxels.rounded is not None
    inexact = fog or scene.voxels.gi is not None or rounded or scene.voxels.ao is not None
    for key in ("image", "radiance", "depth", "alpha"):
        a, b = getattr(fast, key), getattr(slow, key)
        tol = 1e-6 * float(b.abs().max()) if inexact and key in ("image", "radiance") or rounded and key == "depth" else 0.0
        assert float((a - b).abs().max()) <= tol, f"{name}: {key} differs by {float((a - b).abs().max()):.3e}"
    for key, a in slow.aovs.items():
        tol = 1e-6 * float(a.abs().max()) if key == "ao" or (cones and key == "radiance") or rounded else 0.0
        assert float((fast.aovs[key] - a).abs().max()) <= tol, f"{name}: AOV {key} differs"


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fog_of_scenes_with_their_own_cell_ranges(dtype):
    """The fog's table of cell rows (scene · Y − lo_y + j) over grids padded to one shape: three
    fog scenes with different cell ranges and fog in one batch, as eager renders them (float32:
    Dr.Jit's walk, its light within float rounding; float64: eager both)."""
    base = tv.preset("voxel-fog", width=40, height=30)
    other = [tv.load_scene(base, overrides=o) for o in (
        {"voxels.cells": {"min": [-10, -9, -12], "max": [12, 6, 10]}, "voxels.fog.density": 0.09,
         "voxels.fog.base": 2.0, "voxels.fog.scale_height": 3.0, "camera.eye": [-18.0, 9.0, -15.0]},
        {"voxels.cells": {"min": [-6, 3, -20], "max": [20, 30, 7]}, "voxels.fog.density": 0.02,
         "camera.eye": [-25.0, 20.0, -18.0]})]
    scenes = [base, *other]
    fast = tv.render(scenes, seed=[0, 1, 2], dtype=dtype)
    slow = tv.render(scenes, compile="off", seed=[0, 1, 2], dtype=dtype)
    for key in ("image", "radiance", "depth", "alpha"):
        a, b = getattr(fast, key), getattr(slow, key)
        tol = 1e-6 * float(b.abs().max()) if key in ("image", "radiance") else 0.0
        assert float((a - b).abs().max()) <= tol, f"{key} differs by {float((a - b).abs().max()):.3e}"
    assert slow.alpha.mean() > 0.1  # the voxels and their fog are in view
