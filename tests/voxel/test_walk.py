"""The fused DDA walk (`torchvol.voxel.walk`) against the plain one (`dda.traverse`): the same hits,
bitwise, and the same visits, eager and compiled; voxel renders under compile "exact" bitwise eager."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import torchvol as tv
from torchvol.ops.grid_ops import chebyshev_distance
from torchvol.voxel import walk
from torchvol.voxel.dda import hybrid_traverse, traverse

FIELDS = ("hit", "cell", "axis", "t", "material", "steps", "t_exit")


def _world(seed: int, n: int, dtype, *, scenes=2, shape=(6, 7, 8), p=0.12):
    """Random material grids of `scenes` scenes (each its own cell range) and n rays of random
    scenes, some axis-parallel, from inside and outside: (rays, lookup, table arguments, ranges,
    (distance lookup, distance table))."""
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

    return (o, d), lookup, (occ.reshape(-1), base, torch.tensor([Y, X])), (lo[s], hi[s]), (distance, field.reshape(-1))


def _recorder(calls):
    return lambda *args: calls.append([a.clone() for a in args])


def _assert_same_walk(seed, n, dtype, *, max_steps, limited, compiled, block=walk.BLOCK, hybrid=False, late=False):
    """fused_traverse against traverse (with a recording visit) or, `hybrid`, hybrid_traverse (on
    larger, sparser grids, where rays jump)."""
    shape, p = ((14, 12, 16), 0.03) if hybrid else ((6, 7, 8), 0.12)
    (o, d), lookup, table, (lo, hi), (distance, field) = _world(seed, n, dtype, shape=shape, p=p)
    g = torch.Generator().manual_seed(seed)
    t_max = torch.rand(n, generator=g, dtype=dtype) * 12 if limited else None
    t_min = torch.rand(n, generator=g, dtype=dtype) * 6 if late else None  # rays that start part-way
    plain_calls, fused_calls = [], []
    if hybrid:
        plain = hybrid_traverse(o, d, lookup, distance, lo, hi, max_steps=max_steps, t_min=t_min, t_max=t_max)
        fused = walk.fused_traverse(o, d, *table, lo, hi, max_steps=max_steps, t_min=t_min, t_max=t_max,
                                    distance=field, compiled=compiled, block=block)
    else:
        plain = traverse(o, d, lookup, lo, hi, max_steps=max_steps, t_min=t_min, t_max=t_max,
                         visit=_recorder(plain_calls))
        fused = walk.fused_traverse(o, d, *table, lo, hi, max_steps=max_steps, t_min=t_min, t_max=t_max,
                                    visit=_recorder(fused_calls), compiled=compiled, block=block)
    for name in FIELDS:
        a, b = getattr(plain, name), getattr(fused, name)
        assert a.dtype == b.dtype and torch.equal(a, b), \
            f"{name}: {int((a != b).sum())} of {n} rays differ (first at ray {int((a != b).nonzero()[0, 0])})"
    assert len(plain_calls) == len(fused_calls), f"{len(fused_calls)} visit calls, expected {len(plain_calls)}"
    for k, (a, b) in enumerate(zip(plain_calls, fused_calls)):
        for name, x, y in zip(("ids", "cells", "t_in", "t_out", "hit"), a, b):
            assert x.dtype == y.dtype and torch.equal(x, y), f"visit call {k}: {name} differs"
    return plain


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 200), max_steps=st.integers(1, 40), limited=st.booleans(),
       block=st.integers(1, 9), double=st.booleans(), late=st.booleans())
def test_eager_twin_walks_like_traverse(seed, n, max_steps, limited, block, double, late):
    _assert_same_walk(seed, n, torch.float64 if double else torch.float32, max_steps=max_steps, limited=limited,
                      compiled=False, block=block, late=late)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 200), max_steps=st.integers(1, 60), limited=st.booleans(),
       block=st.integers(1, 9), double=st.booleans(), late=st.booleans())
def test_eager_twin_jumps_like_hybrid_traverse(seed, n, max_steps, limited, block, double, late):
    """With the distance field: hybrid_traverse's jumps and steps."""
    _assert_same_walk(seed, n, torch.float64 if double else torch.float32, max_steps=max_steps, limited=limited,
                      compiled=False, block=block, hybrid=True, late=late)


def test_the_comparison_sees_a_wrong_walk(monkeypatch):
    """A walk that keeps its rays one step too long is caught (the test above can fail)."""
    monkeypatch.setattr(walk, "walk_block", _off_by_one(walk.walk_block))
    with pytest.raises(AssertionError, match="differ"):
        _assert_same_walk(5, 300, torch.float32, max_steps=6, limited=False, compiled=False)


def _off_by_one(block):
    def wrong(*args, **kwargs):
        args = list(args)
        args[4] = args[4] + 1  # max_steps
        return block(*args, **kwargs)
    return wrong


@pytest.mark.slow
@pytest.mark.parametrize("limited, visits", [(False, True), (True, False)])
def test_compiled_walk_is_bitwise_the_plain_walk(limited, visits):
    """Compiled, the same bits: the walk is divisions, compares and integer steps, which inductor
    neither contracts nor reorders. Sizes of 1 (a slot run twice) and odd counts included."""
    for seed, n in ((1, 1), (2, 2), (3, 777), (4, 3000)):
        h = _assert_same_walk(seed, n, torch.float32, max_steps=40, limited=limited, compiled=True)
    assert h.hit.any() and (~h.hit).any()


@pytest.mark.slow
def test_compiled_hybrid_walk_is_bitwise_hybrid_traverse():
    for seed, n in ((5, 1), (6, 1500)):
        h = _assert_same_walk(seed, n, torch.float32, max_steps=80, limited=False, compiled=True, hybrid=True)
    assert h.hit.any() and (~h.hit).any()
    (o, d), lookup, _, (lo, hi), _ = _world(6, 1500, torch.float32, shape=(14, 12, 16), p=0.03)
    plain = traverse(o, d, lookup, lo, hi, max_steps=80)
    assert h.steps.sum() < 0.8 * plain.steps.sum(), "the rays did not jump"


VOXEL_PRESETS = [name for name in tv.preset_names() if name.startswith("voxel-")]


@pytest.mark.parametrize("name, overrides", [(name, {}) for name in VOXEL_PRESETS]
                         + [("voxel-fog", {"voxels.traversal": "hybrid"}), ("voxel-glow", {"voxels.traversal": "hybrid"})])
def test_exact_renders_are_eager_renders(name, overrides, monkeypatch):
    """Every walk gives the eager walk's bits: `render(..., compile="exact")` (the fused walk, its
    eager twin here: nothing compiles, for the walks that record their cells; Dr.Jit's for the
    others) and the default (Dr.Jit's walk) render every output bitwise as the eager reference
    does (a fog's light excepted, which Dr.Jit's walk sums with its own exp: within float
    rounding); with fog or glow a hybrid scene walks plainly on every path."""
    monkeypatch.setattr(walk, "compiled_block", lambda: walk.walk_block)
    scene = tv.load_scene(tv.preset(name, width=40, height=30), overrides=overrides)
    slow = tv.render(scene, compile="off")
    assert slow.stats["plan"]["walk"] == "eager"
    fog = scene.voxels.fog is not None and scene.voxels.glow is None
    for mode in ("exact", "auto"):
        fast = tv.render(scene, compile=mode)
        for key in ("image", "radiance", "depth", "alpha"):
            a, b = getattr(fast, key), getattr(slow, key)
            tol = 1e-6 * float(b.abs().max()) if fog and key in ("image", "radiance") else 0.0
            assert float((a - b).abs().max()) <= tol, f"{name}, {mode}: {key} differs by {float((a - b).abs().max()):.3e}"
        for key, a in slow.aovs.items():
            assert torch.equal(fast.aovs[key], a), f"{name}, {mode}: AOV {key} differs"


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fog_of_scenes_with_their_own_cell_ranges(monkeypatch, dtype):
    """The fog's table of cell rows (scene · Y − lo_y + j) over grids padded to one shape: three
    fog scenes with different cell ranges and fog in one batch, bitwise eager."""
    monkeypatch.setattr(walk, "compiled_block", lambda: walk.walk_block)
    base = tv.preset("voxel-fog", width=40, height=30)
    other = [tv.load_scene(base, overrides=o) for o in (
        {"voxels.cells": {"min": [-10, -9, -12], "max": [12, 6, 10]}, "voxels.fog.density": 0.09,
         "voxels.fog.base": 2.0, "voxels.fog.scale_height": 3.0, "camera.eye": [-18.0, 9.0, -15.0]},
        {"voxels.cells": {"min": [-6, 3, -20], "max": [20, 30, 7]}, "voxels.fog.density": 0.02,
         "camera.eye": [-25.0, 20.0, -18.0]})]
    scenes = [base, *other]
    fast = tv.render(scenes, compile="exact", seed=[0, 1, 2], dtype=dtype)
    slow = tv.render(scenes, seed=[0, 1, 2], dtype=dtype)
    for key in ("image", "radiance", "depth", "alpha"):
        a, b = getattr(fast, key), getattr(slow, key)
        assert torch.equal(a, b), f"{key} differs by {float((a - b).abs().max()):.3e}"
    assert slow.alpha.mean() > 0.1  # the voxels and their fog are in view


def test_exact_recipe_batches_are_eager_batches(monkeypatch):
    """Recipe samples (voxel-terrain: its fog, sun shadows and clouds) in one batch:
    `compile="exact"` samples, bitwise the eager ones."""
    from pathlib import Path

    from torchvol.dataset.datasets import render_samples
    from torchvol.dataset.recipe import Recipe

    monkeypatch.setattr(walk, "compiled_block", lambda: walk.walk_block)
    recipe = Recipe.load(Path(__file__).resolve().parents[2] / "datasets" / "voxel-terrain.toml",
                         {"image.width": 24, "image.height": 16})
    fast, slow = render_samples(recipe, [0, 1, 2], compile="exact"), render_samples(recipe, [0, 1, 2])
    for a, b in zip(fast, slow):
        for key in ("image", "depth", "alpha"):
            assert torch.equal(a[key], b[key]), f"sample {a['index']}: {key} differs"


@pytest.mark.slow
def test_exact_render_compiled_is_eager(one_thread):
    scene = tv.preset("voxel-fog", width=48, height=32)
    fast, slow = tv.render(scene, compile="exact"), tv.render(scene)
    for key in ("image", "depth", "alpha"):
        a, b = getattr(fast, key), getattr(slow, key)
        assert torch.equal(a, b), f"{key} differs by {float((a - b).abs().max()):.3e}"


def test_a_walk_that_cannot_compile_walks_eagerly(tmp_path):
    """No C++ compiler (CXX names none, inductor's cache empty): `compile="exact"` warns once and
    renders eagerly, the same bits, instead of failing where eager runs (voxel-fog: its primary
    walk calls the glow's callback at every cell, which Dr.Jit's walk does not)."""
    import os
    import subprocess
    import sys

    code = """
import warnings, torch, torchvol as tv
scene = tv.preset("voxel-glow", width=12, height=8)
with warnings.catch_warnings(record=True) as seen:
    warnings.simplefilter("always")
    fast = tv.render(scene, compile="exact")
slow = tv.render(scene)
walk = [str(w.message) for w in seen if "voxel walk could not be compiled" in str(w.message)]
assert len(walk) == 1, [str(w.message) for w in seen]
assert torch.equal(fast.image, slow.image) and torch.equal(fast.depth, slow.depth)
print("fell back")
"""
    env = {**os.environ, "CXX": str(tmp_path / "no-such-compiler"), "TORCHINDUCTOR_CACHE_DIR": str(tmp_path / "cache")}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and "fell back" in out.stdout, out.stderr[-2000:]


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 200), max_steps=st.integers(1, 60), limited=st.booleans(),
       late=st.booleans(), hybrid=st.booleans())
def test_the_drjit_walk_is_bitwise_the_plain_walk(seed, n, max_steps, limited, late, hybrid):
    """`walk.drjit_traverse`: the block's own step (`walk_step`, lanes) in one Dr.Jit loop per ray;
    float32 rays, axis-parallel ones and rays that start inside or part-way included."""
    from torchvol.runtime.compilation import drjit_available

    if not drjit_available():
        pytest.skip("Dr.Jit's LLVM backend is not available")
    shape, p = ((14, 12, 16), 0.03) if hybrid else ((6, 7, 8), 0.12)
    (o, d), lookup, table, (lo, hi), (distance, field) = _world(seed, n, torch.float32, shape=shape, p=p)
    g = torch.Generator().manual_seed(seed)
    t_max = torch.rand(n, generator=g) * 12 if limited else None
    t_min = torch.rand(n, generator=g) * 6 if late else None
    if hybrid:
        plain = hybrid_traverse(o, d, lookup, distance, lo, hi, max_steps=max_steps, t_min=t_min, t_max=t_max)
    else:
        plain = traverse(o, d, lookup, lo, hi, max_steps=max_steps, t_min=t_min, t_max=t_max)
    kernel = walk.drjit_traverse(o, d, *table, lo, hi, max_steps=max_steps, t_min=t_min, t_max=t_max,
                                 distance=field if hybrid else None)
    for name in FIELDS:
        a, b = getattr(plain, name), getattr(kernel, name)
        assert a.dtype == b.dtype and torch.equal(a, b), \
            f"{name}: {int((a != b).sum())} of {n} rays differ (first at ray {int((a != b).nonzero()[0, 0])})"
