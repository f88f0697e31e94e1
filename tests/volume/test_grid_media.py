"""Grid media: the exact lattice integrals against closed forms, empty-space skipping against the
full march, the sun grid and the fast render against the exact float64 reference."""

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from conftest import TOL, assert_close
from hypothesis import given, settings
from hypothesis import strategies as st

import torchvol as tv
from torchvol.fields.grid import (
    Grid,
    grid_density,
    grid_lanes,
    grid_occupancy,
    sample_grid,
)
from torchvol.geometry.rays import intersect_box
from torchvol.light.phase import henyey_greenstein
from torchvol.measure.mitsuba import (
    IRRADIANCE,
    SUN,
    puff_grid,
    relative_rmse,
    sigma_for,
    torchvol_scene,
)
from torchvol.ops import lanes
from torchvol.ops.lanes import per_scene_lanes
from torchvol.renderer import plan
from torchvol.renderer.executor import camera_for
from torchvol.runtime.compilation import drjit_available
from torchvol.schema.batch import stack, take
from torchvol.volume.exact import grid_optical_depth, grid_single_scatter
from torchvol.volume.skip import macro_grid, occupied_span
from torchvol.volume.sun_volume import sun_transmittance_grid

F64 = torch.float64
LO, HI = torch.tensor([-1.0, -0.5, -0.8], dtype=F64), torch.tensor([1.0, 0.7, 0.6], dtype=F64)


def random_rays(n: int, seed: int, *, axis_parallel: bool = False):
    g = torch.Generator().manual_seed(seed)
    origins = torch.randn(n, 3, generator=g, dtype=F64) * 3
    targets = LO + (HI - LO) * torch.rand(n, 3, generator=g, dtype=F64)
    d = torch.nn.functional.normalize(targets - origins, dim=1)
    if axis_parallel:  # through the box along one axis, exactly
        axis = torch.arange(n) % 3
        d = torch.zeros(n, 3, dtype=F64)
        d[torch.arange(n), axis] = 1.0
        origins = targets - 5.0 * d
    return origins, d


@pytest.mark.parametrize("axis_parallel", [False, True])
def test_optical_depth_of_a_constant_grid_is_sigma_times_the_chord(axis_parallel):
    grid = torch.full((5, 7, 6), 2.5, dtype=F64)
    o, d = random_rays(300, 0, axis_parallel=axis_parallel)
    t0, t1 = intersect_box(o, d, LO, HI)
    t0 = t0.clamp_min(0)
    assert_close(grid_optical_depth(grid, LO, HI, o, d, t0, t1), 2.5 * (t1 - t0), atol=TOL[F64] * 10, what="optical depth")


def test_optical_depth_of_a_linear_grid_is_exact_between_the_outer_centres():
    n = (6, 5, 8)  # (D, H, W)
    size = (HI - LO) / torch.tensor([n[2], n[1], n[0]], dtype=F64)
    centres = [LO[a] + (torch.arange(k, dtype=F64) + 0.5) * size[a] for a, k in enumerate((n[2], n[1], n[0]))]
    z, y, x = torch.meshgrid(centres[2], centres[1], centres[0], indexing="ij")
    grid = 1.0 + 0.3 * x - 0.7 * y + 0.2 * z  # trilinear reproduces it between the first and last centres
    o, d = random_rays(200, 1)
    inner_lo, inner_hi = LO + 0.5 * size, HI - 0.5 * size
    t0, t1 = intersect_box(o, d, inner_lo, inner_hi)
    keep = t1 > t0.clamp_min(0)
    o, d, t0, t1 = o[keep], d[keep], t0[keep].clamp_min(0), t1[keep]
    f = lambda t: 1.0 + (o + t[:, None] * d) @ torch.tensor([0.3, -0.7, 0.2], dtype=F64) - 1.0  # noqa: E731
    exact = (t1 - t0) * (1.0 + 0.5 * (f(t0) + f(t1)))  # a linear integrand: length × midpoint value
    assert_close(grid_optical_depth(grid, LO, HI, o, d, t0, t1), exact, atol=1e-12, what="optical depth")


def test_single_scatter_of_a_constant_grid_matches_the_closed_form():
    """Rays along +z at height y, sun straight up: L = p(90°)·E·albedo·e^{−σ(y_max − y)}·(1 − e^{−σ·chord})."""
    sigma, albedo, E, g = 3.0, 0.8, 2.0, 0.6
    grid = torch.ones(4, 6, 5, dtype=F64)
    ys = torch.linspace(-0.45, 0.65, 12, dtype=F64)
    o = torch.stack([torch.full_like(ys, 0.1), ys, torch.full_like(ys, -3.0)], 1)
    d = torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand_as(o)
    phase = lambda c: henyey_greenstein(c, torch.full_like(c, g))  # noqa: E731
    L, T = grid_single_scatter(grid, LO, HI, o, d, sigma_t=sigma, albedo=albedo, sun=torch.tensor([0.0, 1.0, 0.0], dtype=F64),
                               irradiance=E, phase=phase)
    chord = HI[2] - LO[2]
    expected = phase(torch.zeros(1, dtype=F64)) * E * albedo * torch.exp(-sigma * (HI[1] - ys)) * -torch.expm1(-sigma * chord)
    assert_close(L, expected, what="radiance")  # Gauss-Legendre on e^{−σt}: not exact, to ~1e-10
    assert_close(T, torch.exp(-sigma * chord).expand_as(T), atol=1e-12, what="transmittance")


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), fill=st.floats(0.02, 0.5), axis_parallel=st.booleans())
def test_occupied_span_holds_every_occupied_point(seed, fill, axis_parallel):
    g = torch.Generator().manual_seed(seed)
    grid = (torch.rand(9, 7, 11, generator=g, dtype=F64) < fill).to(F64)
    macro = macro_grid(grid_occupancy(grid), LO, HI, cells=4)  # 11, 7, 9 cells: pooled by 3, not dividing
    o, d = random_rays(64, seed, axis_parallel=axis_parallel)
    t0, t1 = intersect_box(o, d, LO, HI)
    t0, hit = t0.clamp_min(0), t1 > t0.clamp_min(0)
    o, d, t0, t1 = o[hit], d[hit], t0[hit], t1[hit]
    first, last, found = occupied_span(o, d, t0, t1, macro, LO)
    t = t0[:, None] + (t1 - t0)[:, None] * torch.linspace(0, 1, 801, dtype=F64)  # [R, 801]
    density = sample_grid(grid, LO, HI, (o[:, None] + t[..., None] * d[:, None]).reshape(-1, 3)).reshape(t.shape)
    outside = (density > 0) & ((t < first[:, None] - 1e-9) | (t > last[:, None] + 1e-9) | ~found[:, None])
    assert not outside.any(), f"density {density[outside].max():.3g} outside the span of ray {outside.any(1).nonzero()[0].item()}"


@pytest.mark.parametrize("thin_axis", [0, 1, 2])
def test_occupied_span_in_a_box_thin_along_one_axis(thin_axis):
    """A box 1e-7 thick: rays along its plane cross many cells of the other axes but the samples
    per ray stay bounded by the cells crossed (a spacing set by the thin axis alone would ask for
    ~1e9 per ray), and the span still holds every point with density."""
    lo, hi = LO.clone(), HI.clone()
    hi[thin_axis] = lo[thin_axis] + 1e-7
    grid = (torch.rand(9, 7, 11, generator=torch.Generator().manual_seed(1), dtype=F64) < 0.2).to(F64)
    macro = macro_grid(grid_occupancy(grid), lo, hi)
    g = torch.Generator().manual_seed(2)
    targets = lo + (hi - lo) * torch.rand(64, 3, generator=g, dtype=F64)
    d = torch.randn(64, 3, generator=g, dtype=F64)
    d[:, thin_axis] *= torch.linspace(0.0, 1e-3, 64, dtype=F64)  # from exactly along the plane to slightly across
    d = torch.nn.functional.normalize(d, dim=1)
    o = targets - 4.0 * d
    t0, t1 = intersect_box(o, d, lo, hi)
    t0, hit = t0.clamp_min(0), t1 > t0.clamp_min(0)
    o, d, t0, t1 = o[hit], d[hit], t0[hit], t1[hit]
    first, last, found = occupied_span(o, d, t0, t1, macro, lo)
    t = t0[:, None] + (t1 - t0)[:, None] * torch.linspace(0, 1, 801, dtype=F64)
    density = sample_grid(grid, lo, hi, (o[:, None] + t[..., None] * d[:, None]).reshape(-1, 3)).reshape(t.shape)
    outside = (density > 0) & ((t < first[:, None] - 1e-9) | (t > last[:, None] + 1e-9) | ~found[:, None])
    assert hit.sum() > 32 and not outside.any(), f"{int(hit.sum())} rays hit; density outside the span: {int(outside.sum())} points"


def _two_grids(dtype):
    """A `Grid` of two scenes' grids of other shapes (one a single cell along x) in other boxes,
    and points [N, 3] of its scenes [N]: random in and around each box, on its faces, edges and
    corners exactly, at every cell centre, just outside a face, far away, infinite and NaN."""
    g = torch.Generator().manual_seed(11)
    arrays = [torch.rand(5, 3, 7, generator=g, dtype=F64), torch.rand(2, 6, 1, generator=g, dtype=F64) + 0.5]
    lo = torch.tensor([[-1.0, -0.5, -0.8], [0.1, 0.2, 0.3]], dtype=dtype)
    hi = torch.tensor([[1.0, 0.7, 0.6], [0.9, 1.2, 0.35]], dtype=dtype)
    field = Grid(stack([tv.load_scene({"volumes": [{"density": {"grid": {"data": a.numpy()}}}]}).volumes[0].density.value
                        for a in arrays], dtype=dtype), torch.zeros(2, dtype=dtype), box_min=lo, box_max=hi)
    units, scenes = [], []
    for b, a in enumerate(arrays):
        cells = torch.tensor(a.shape[::-1], dtype=dtype)
        centres = torch.cartesian_prod(*[(torch.arange(int(n), dtype=dtype) + 0.5) / n for n in cells])
        face = torch.rand(3000, 3, generator=g, dtype=dtype)
        axis = torch.arange(3000) % 3
        face[torch.arange(3000), axis] = (torch.arange(3000) // 3 % 2).to(dtype)  # on a face: 0 or 1 along one axis
        corners = torch.randint(0, 2, (64, 3), generator=g).to(dtype)
        outside = face.clone()
        outside[torch.arange(3000), axis] += torch.where(outside[torch.arange(3000), axis] > 0, 1e-3, -1e-3).to(dtype)
        odd = torch.tensor([[1e7, 0.5, 0.5], [-1e30, 0.5, 0.5], [0.5, math.inf, 0.5], [0.5, 0.5, -math.inf],
                            [math.nan, 0.5, 0.5]], dtype=dtype)
        u = torch.cat([torch.rand(20000, 3, generator=g, dtype=dtype) * 1.4 - 0.2, face, corners, centres, outside, odd])
        units.append(u)
        scenes.append(torch.full((u.shape[0],), b))
    s = torch.cat(scenes)
    p = take(lo, s) + torch.cat(units) * take(hi - lo, s)
    return field, p, s, torch.cat(units)


def _sample_grid_per_scene(field: Grid, p, s):
    out = torch.empty(p.shape[0], dtype=p.dtype)
    for b in range(len(field.grids)):
        out[s == b] = sample_grid(field.grids[b], field.box_min[b], field.box_max[b], p[s == b])
    return out


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_the_grid_in_lanes_is_grid_sample_bitwise_on_torch(dtype):
    """`grid_density` on torch columns against the eager field's `grid_sample` (`sample_grid`),
    two scenes of other shapes in one table: bitwise, on the faces and outside too. A cell centre
    reads its own cell's value; a face the edge cells' (border padding), a hair outside it 0."""
    field, p, s, unit = _two_grids(dtype)
    to = SimpleNamespace(per_lane=lambda v: lanes.columns(take(v, s)), scene=s, floats=lambda t: t, ints=lambda t: t)
    got = grid_density(grid_lanes(field, to), list(p.unbind(1)), None)
    expected = _sample_grid_per_scene(field, p, s)
    assert torch.equal(got, expected), f"{int((got != expected).sum())} differ, by up to {float((got - expected).abs().max()):.3g}"
    inside = ((unit >= 0) & (unit <= 1)).all(dim=1)
    assert bool((got[~inside] == 0).all()) and bool((got[inside] > 0).all())  # the test's grids are > 0 in scene 1
    for b, a in enumerate(field.grids):
        n = a.numel()
        at_centres = (s == b).nonzero().squeeze(1)[20000 + 3000 + 64:][:n]  # `cartesian_prod` order: x slowest
        i, j, k = torch.meshgrid(*[torch.arange(m) for m in a.shape[::-1]], indexing="ij")
        assert_close(got[at_centres], a[k.reshape(-1), j.reshape(-1), i.reshape(-1)], atol=10 * torch.finfo(dtype).eps,
                     what=f"scene {b}'s values at its cell centres")  # (a centre's position rounds)


@pytest.mark.skipif(not drjit_available(), reason="Dr.Jit's LLVM backend is not available")
def test_the_grid_in_lanes_traced_by_drjit_is_grid_sample_bitwise():
    """`grid_density` traced by Dr.Jit over the inputs a kernel builds (`ops.lanes.lanes_inputs`:
    the batch's grids one table, each lane's scene's offset and cells) against `sample_grid`."""
    import numpy as np
    from drjit.llvm import Float

    field, p, s, _ = _two_grids(torch.float32)
    q = grid_lanes(field, lanes.lanes_inputs(s, per_scene_lanes(s)))
    got = torch.from_numpy(np.array(grid_density(q, [Float(c.contiguous().numpy()) for c in p.unbind(1)], None)))
    expected = _sample_grid_per_scene(field, p, s)
    assert torch.equal(got, expected), f"{int((got != expected).sum())} differ, by up to {float((got - expected).abs().max()):.3g}"


def parity_rays(size: int):
    scene = tv.load_scene(torchvol_scene(puff_grid(32), 1.0, size=size, spp=1))
    return camera_for(stack([scene], dtype=F64)).rays()


def exact_parity(size: int):
    grid = puff_grid(32)
    sigma = sigma_for(grid)
    rays = parity_rays(size)
    L, _ = grid_single_scatter(torch.as_tensor(grid), -torch.ones(3, dtype=F64), torch.ones(3, dtype=F64), rays.origins, rays.directions,
                               sigma_t=sigma, albedo=0.9, sun=torch.tensor(SUN, dtype=F64), irradiance=IRRADIANCE,
                               phase=lambda c: henyey_greenstein(c, torch.full_like(c, 0.8)))
    return grid, sigma, L.reshape(size, size).numpy()


def skip_cases() -> dict[str, list[dict]]:
    grid = puff_grid(24)
    sigma = sigma_for(grid)
    base = lambda g=grid, **kw: torchvol_scene(g, sigma, size=16, spp=1, steps=48, **kw)  # noqa: E731
    inside, empty, sized = base(), base(np.zeros_like(grid)), base()
    inside["camera"]["eye"] = [0.1, 0.05, -0.2]  # rays start inside occupied cells
    sized["march"] = {"placement": "size", "step_size": 0.03}
    return {"outside": [base()], "camera inside": [inside], "empty grid": [empty], "size placement": [sized],
            "batch of two grids": [base(), base(puff_grid(24, seed=5))]}


@pytest.mark.parametrize("case, compile", [(case, "off") for case in skip_cases()] + [("size placement", "kernels")])
def test_skipping_empty_space_changes_the_cost_not_the_image(case, compile, monkeypatch):
    """In the eager march, and in the Dr.Jit kernel where it skips too (`plan.kernel_strategy`)."""
    scenes = skip_cases()[case]
    skipped = tv.render(scenes, compile=compile)
    decide = plan.strategy  # the plan decides: the same march without the skip pass
    monkeypatch.setattr(plan, "strategy", lambda *a: "march" if decide(*a) == "skip" else decide(*a))
    full = tv.render(scenes, compile=compile)
    backend = "eager" if compile == "off" or not drjit_available() else "drjit"
    assert skipped.stats["plan"]["marches"] == full.stats["plan"]["marches"] == {"volume0": backend}
    assert "volume0.skip" in skipped.stats["passes"] and "volume0.skip" not in full.stats["passes"]
    assert skipped.stats["march_steps"] < 0.85 * full.stats["march_steps"], (skipped.stats["march_steps"], full.stats["march_steps"])
    assert_close(skipped.radiance, full.radiance, atol=2e-6, what="radiance")
    assert_close(skipped.depth, full.depth, atol=2e-5, what="depth")


def test_sun_grid_transmittance_against_the_exact_one():
    grid = torch.as_tensor(puff_grid(32))
    sigma = sigma_for(grid.numpy())
    box = -torch.ones(3, dtype=F64), torch.ones(3, dtype=F64)
    sun = torch.tensor(SUN, dtype=F64)
    ext = lambda p: sigma * sample_grid(grid, *box, p)  # noqa: E731
    table = sun_transmittance_grid(ext, *box, sun, resolution=96)
    g = torch.Generator().manual_seed(3)
    points = torch.rand(4000, 3, generator=g, dtype=F64) * 1.8 - 0.9
    points = points[ext(points) > 0]
    towards = sun.expand_as(points)
    exit_t = intersect_box(points, towards, *box)[1]
    exact = torch.exp(-sigma * grid_optical_depth(grid, *box, points, towards, torch.zeros_like(exit_t), exit_t))
    err = (table.lookup(points, ext(points)) - exact).abs()
    assert err.mean() < 2e-3, f"mean |ΔT| {err.mean():.2e}"
    assert err.max() < 2e-2, f"max |ΔT| {err.max():.2e} at {points[err.argmax()].tolist()}"


@pytest.mark.parametrize("method, bound", [("march", 1e-3), ("grid", 2e-3)])  # measured 0.04%, 0.08%
def test_render_agrees_with_the_exact_reference(method, bound):
    grid, sigma, exact = exact_parity(24)
    scene = torchvol_scene(grid, sigma, size=24, spp=1, steps=128, shadow_steps=32)
    scene["lights"][0]["shadow"]["method"] = method
    image = tv.render(scene).radiance[0, 0].numpy()
    err = relative_rmse(image, exact)
    assert err < bound, f"shadow {method}: relative RMSE {err:.3%} against the exact reference"
    assert math.isfinite(err)
