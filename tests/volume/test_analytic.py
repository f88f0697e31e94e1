"""Analytic ground truth for the volume renderer.

Every expected value here is computed independently of the renderer: rays are rebuilt in numpy
float64 from the exported `out.camera.K` / `world_to_camera` (direction = Rᵀ K⁻¹ [u, v, 1] at the
pixel centres u = column, v = row), chords come from our own sphere / box / slab geometry, and the
media have closed-form optical depths (Beer-Lambert, exponential height profile, a linear grid
ramp with clamp-to-edge half cells).

Near silhouettes and box edges the chord is ill-conditioned (an ulp of ray direction changes it a
lot), so the float32 comparisons use only the pixels whose expected value is stable under a tiny
perturbation of the ray (`well_conditioned`), and assert that those are the large majority.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import TOL, assert_close

import torchvol as tv
from torchvol.geometry.camera import Camera
from torchvol.geometry.rays import clip_to_ray, intersect_box, intersect_sphere
from torchvol.volume.march import StepRule, march

F32, F64 = torch.float32, torch.float64
LN2 = math.log(2.0)

# ---------------------------------------------------------------------------------------------
# Independent geometry (numpy float64)


def camera_rays(out, b: int = 0):
    """Eye [3], unit directions [H, W, 3] and forward cosines [H, W] of scene b, rebuilt from the
    exported K and world_to_camera."""
    cam = out.camera
    K = cam.K[b].double().numpy()
    w2c = cam.world_to_camera[b].double().numpy()
    R, t = w2c[:3, :3], w2c[:3, 3]
    eye = -R.T @ t
    v, u = np.meshgrid(np.arange(cam.height, dtype=np.float64), np.arange(cam.width, dtype=np.float64), indexing="ij")
    pix = np.stack([u, v, np.ones_like(u)], axis=-1)  # [H, W, 3]
    d_cam = pix @ np.linalg.inv(K).T
    norm = np.linalg.norm(d_cam, axis=-1)
    d_world = (d_cam @ R) / norm[..., None]  # Rᵀ d as row vectors
    return eye, d_world, d_cam[..., 2] / norm


def sphere_interval(o, d, center, radius):
    """Entry/exit of the closed ball along unit rays, clipped to t ≥ 0. -> t0, t1, hit [...]"""
    oc = np.asarray(o, np.float64) - np.asarray(center, np.float64)
    b = (oc * d).sum(-1)
    perp = oc - b[..., None] * d
    disc = radius * radius - (perp * perp).sum(-1)
    s = np.sqrt(np.clip(disc, 0.0, None))
    t0 = np.maximum(-b - s, 0.0)
    t1 = -b + s
    hit = (disc >= 0) & (t1 > t0)
    return np.where(hit, t0, 0.0), np.where(hit, t1, 0.0), hit


def box_interval(o, d, lo, hi):
    o = np.broadcast_to(np.asarray(o, np.float64), d.shape)
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (lo - o) / d
        c = (hi - o) / d
    par = d == 0
    inside = (o >= lo) & (o <= hi)
    tl = np.where(par, np.where(inside, -np.inf, np.inf), np.minimum(a, c))
    th = np.where(par, np.where(inside, np.inf, -np.inf), np.maximum(a, c))
    t0 = np.maximum(tl.max(-1), 0.0)
    t1 = th.min(-1)
    hit = t1 > t0
    return np.where(hit, t0, 0.0), np.where(hit, t1, 0.0), hit


def slab_interval(o, d, y0, y1):
    return box_interval(o, d, [-np.inf, y0, -np.inf], [np.inf, y1, np.inf])


def random_perpendicular(d, rng):
    x = rng.normal(size=d.shape)
    x -= (x * d).sum(-1, keepdims=True) * d
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def well_conditioned(expected_fn, eye, dirs, *, rel=1e-6, scale=1.0, tol=3e-5, seed=0):
    """Pixels whose expected value moves by < tol when the ray moves by ~rel (an ulp-sized
    perturbation of float32 rays, with margin). `expected_fn(eye, dirs) -> [H, W]`."""
    rng = np.random.default_rng(seed)
    base = expected_fn(eye, dirs)
    spread = np.zeros_like(base)
    for _ in range(4):
        dd = dirs + rel * random_perpendicular(dirs, rng)
        dd /= np.linalg.norm(dd, axis=-1, keepdims=True)
        ee = np.asarray(eye) + rel * scale * rng.normal(size=3)
        spread = np.maximum(spread, np.abs(expected_fn(ee, dd) - base))
    return spread < tol


def up_for(eye, target):
    f = np.subtract(target, eye)
    f = f / np.linalg.norm(f)
    return [0.0, 0.0, 1.0] if abs(f[1]) > 0.95 else [0.0, 1.0, 0.0]


def scene(eye, target, bounds, *, sigma, width=12, height=10, fov=50.0, density=None, march=None, **vol):
    v = {"bounds": bounds, "density": density or {"constant": 1.0}, "sigma_t": sigma, "albedo": 0.0, **vol}
    s = {
        "image": {"width": width, "height": height},
        "camera": {"eye": list(map(float, eye)), "target": list(map(float, target)), "up": up_for(eye, target), "fov_y": fov},
        "volumes": [v],
    }
    if march is not None:
        s["march"] = march
    return s


# ---------------------------------------------------------------------------------------------
# Beer-Lambert through homogeneous spheres and boxes

CENTER = np.array([0.3, -0.2, 0.1])
RADIUS = 1.0
BOX_LO, BOX_HI = np.array([-0.6, -0.4, -0.5]), np.array([0.5, 0.7, 0.4])
SIGMAS = [1e-3, 0.1, 1.0, 10.0, 1e3]


def _around(center, dist):
    dirs = [(1, 0.3, -2), (-1, 0.5, 1), (0.2, -1, 0.4), (0.05, 3, -0.1), (2, -0.2, 0.1), (-0.7, -0.4, -1)]
    return [center + dist * np.asarray(v, float) / np.linalg.norm(v) for v in dirs]


def _views(kind):
    """(eye, target, label): outside from many angles, inside, and exactly on the boundary."""
    if kind == "sphere":
        c = CENTER
        views = [(e, c, "outside") for e in _around(c, 3.5)]
        views += [(c + [0.2, 0.1, -0.3], c + [1.0, 0.3, 2.0], "inside"), (c, c + [0.0, 0.0, 1.0], "inside-centre")]
        # points exactly representable on the sphere: centre ± radius along an axis
        views += [(c + [0.0, 0.0, -RADIUS], c, "on-boundary-in"), (c + [RADIUS, 0.0, 0.0], c + [2.0, 0.5, 1.0], "on-boundary-out")]
        views += [(c + [0.0, RADIUS, 0.0], c + [1.0, 0.2, 0.3], "on-boundary-tangent")]
        return views
    mid = 0.5 * (BOX_LO + BOX_HI)
    views = [(e, mid, "outside") for e in _around(mid, 3.0)]
    views += [(mid + [0.1, -0.1, 0.05], mid + [1.0, 0.4, -2.0], "inside"), (mid, mid + [0.3, 0.2, 1.0], "inside-centre")]
    views += [(np.array([0.1, 0.2, BOX_LO[2]]), mid, "on-face-in"), (np.array([BOX_HI[0], 0.1, 0.0]), [2.0, 0.3, 0.5], "on-face-out")]
    views += [(BOX_LO.copy(), BOX_HI, "on-corner-in")]
    return views


def _bounds(kind):
    if kind == "sphere":
        return {"sphere": {"center": CENTER.tolist(), "radius": RADIUS}}
    return {"box": {"min": BOX_LO.tolist(), "max": BOX_HI.tolist()}}


def _interval(kind, eye, dirs):
    if kind == "sphere":
        return sphere_interval(eye, dirs, CENTER, RADIUS)
    return box_interval(eye, dirs, BOX_LO, BOX_HI)


@pytest.mark.parametrize("kind", ["sphere", "box"])
@pytest.mark.parametrize("mode", ["closed_form", "march"])
def test_beer_lambert_alpha_float32(kind, mode):
    views = _views(kind)
    # frostbite's transmittance is exact for a constant medium at any step count: few steps suffice
    march_keys = None if mode == "closed_form" else {"closed_form": False, "steps": 12}
    scenes = [scene(e, t, _bounds(kind), sigma=s, march=march_keys) for e, t, _ in views for s in SIGMAS]
    out = tv.render(scenes)
    assert out.stats["passes"][1] == f"volume0.{mode}"
    # forced march: early termination at T < 1e-4 keeps alpha within 1e-4 (+ float32 rounding)
    atol = TOL[F32] + (2e-6 if mode == "march" else 0.0)
    kept_total = 0
    for b, (view, sigma) in enumerate((v, s) for v in views for s in SIGMAS):
        eye, dirs, _ = camera_rays(out, b)

        def expected(e, d, sigma=sigma):
            t0, t1, hit = _interval(kind, e, d)
            return -np.expm1(-sigma * (t1 - t0))

        want = torch.from_numpy(expected(eye, dirs)).float()
        got = out.alpha[b, 0]
        if view[2].endswith("-out"):
            # eye on the boundary looking out of the volume: nothing in front, up to the float32
            # rounding of the eye itself (rebuilt from world_to_camera), ~1e-7 world units
            assert_close(got, 0.0, atol=max(TOL[F32], -math.expm1(-sigma * 1e-5)), what=f"{kind} {view[2]} σ={sigma:g}")
            kept_total += got.numel()
            continue
        good = well_conditioned(expected, eye, dirs, scale=4.0)
        kept_total += good.sum()
        assert good.mean() > 0.7, f"{view[2]} σ={sigma}: only {good.mean():.0%} of pixels well conditioned"
        assert_close(
            torch.where(torch.from_numpy(good), got, want), want, atol=atol,
            what=f"{kind} {mode} alpha, view {b // len(SIGMAS)} ({view[2]}), σ={sigma:g}",
        )
    assert kept_total > 0.85 * out.alpha.numel()


@pytest.mark.parametrize("kind", ["sphere", "box"])
def test_beer_lambert_render_float64_holds_float32(kind):
    """Rendering in float64 gives alpha equal to the analytic value to float32's resolution."""
    views = _views(kind)
    scenes = [scene(e, t, _bounds(kind), sigma=s) for e, t, _ in views for s in SIGMAS]
    out = tv.render(scenes, dtype=F64)
    assert out.camera.K.dtype == F64
    for b, (view, sigma) in enumerate((v, s) for v in views for s in SIGMAS):
        eye, dirs, _ = camera_rays(out, b)
        t0, t1, hit = _interval(kind, eye, dirs)
        want = torch.from_numpy(-np.expm1(-sigma * (t1 - t0))).float()
        # float64 rays: conditioning costs ~1e-16·cond, far below float32's half ulp (6e-8)
        good = torch.from_numpy(well_conditioned(lambda e, d: -np.expm1(-sigma * np.subtract(*_interval(kind, e, d)[1::-1])),
                                                 eye, dirs, rel=1e-12, scale=4.0, tol=1e-8))
        assert_close(torch.where(good, out.alpha[b, 0], want), want, atol=2e-7,
                     what=f"{kind} float64 render alpha, view {view[2]}, σ={sigma:g}")


@pytest.mark.parametrize("kind", ["sphere", "box"])
@pytest.mark.parametrize("integrator", ["riemann", "frostbite"])
def test_beer_lambert_functional_core_float64(kind, integrator):
    """intersection + march with a constant medium, float64: transmittance to 1e-9."""
    for eye, target, label in _views(kind):
        cam = Camera.look_at(torch.tensor(eye, dtype=F64), torch.tensor(np.asarray(target, float), dtype=F64),
                             torch.tensor(up_for(eye, target), dtype=F64), width=9, height=7, fov_y=torch.tensor(55.0, dtype=F64))
        rays = cam.rays()
        if kind == "sphere":
            tn, tf = intersect_sphere(rays.origins, rays.directions, torch.tensor(CENTER), RADIUS)
        else:
            tn, tf = intersect_box(rays.origins, rays.directions, torch.tensor(BOX_LO), torch.tensor(BOX_HI))
        t0, t1, hit = clip_to_ray(tn, tf)
        o = rays.origins[0].numpy()
        d = rays.directions.numpy()
        e0, e1, ehit = _interval(kind, o, d)
        chord = e1 - e0
        for sigma in SIGMAS:
            def medium(ids, t, dt, sigma=sigma):
                return torch.full_like(t, sigma), torch.zeros(t.shape[0], 3, dtype=t.dtype)

            res = march(t0, t1, hit, medium, rule=StepRule("count", 7), integrator=integrator)
            assert_close(res.transmittance, torch.from_numpy(np.exp(-sigma * chord)), atol=TOL[F64],
                         what=f"{kind} {label} σ={sigma:g} float64 transmittance")
            assert res.transmittance.dtype == F64


# ---------------------------------------------------------------------------------------------
# Constant source: emission E, albedo 0, no lights -> L = E·ρ/σ·(1 − e^{−σ ρ d})


def _emissive_scenes(sigma, density, march_keys):
    c = CENTER
    return [
        scene(e, c, _bounds("sphere"), sigma=sigma, density={"constant": density}, emission=[0.2, 0.5, 0.9], march=march_keys)
        for e in _around(c, 3.0)[:3]
    ] + [scene(c + [0.1, 0.2, 0.0], c + [0.0, 0.0, 2.0], _bounds("sphere"), sigma=sigma, density={"constant": density},
               emission=[0.2, 0.5, 0.9], march=march_keys)]


def _emissive_expected(out, b, sigma, density):
    eye, dirs, _ = camera_rays(out, b)
    t0, t1, hit = sphere_interval(eye, dirs, CENTER, RADIUS)
    ext = sigma * density
    frac = -np.expm1(-ext * (t1 - t0))
    E = np.array([0.2, 0.5, 0.9])
    return torch.from_numpy((E[:, None, None] * density / ext) * frac[None]).float(), eye, dirs


@pytest.mark.parametrize("sigma,density", [(0.5, 1.0), (2.0, 0.7), (30.0, 1.0), (1e3, 2.0)])
@pytest.mark.parametrize("mode", ["closed_form", "frostbite_3_steps"])
def test_constant_source_exact(sigma, density, mode):
    march_keys = None if mode == "closed_form" else {"closed_form": False, "integrator": "frostbite", "steps": 3,
                                                      "placement": "count", "min_transmittance": 0.0}
    scenes = _emissive_scenes(sigma, density, march_keys)
    out = tv.render(scenes)
    assert out.stats["passes"][1] == ("volume0.closed_form" if mode == "closed_form" else "volume0.march")
    for b in range(len(scenes)):
        want, eye, dirs = _emissive_expected(out, b, sigma, density)

        def expected(e, d):
            t0, t1, _ = sphere_interval(e, d, CENTER, RADIUS)
            return 0.9 / sigma * -np.expm1(-sigma * density * (t1 - t0))

        good = torch.from_numpy(well_conditioned(expected, eye, dirs, scale=4.0))
        assert good.float().mean() > 0.7
        # radiance is bounded by E/σ; compare relative to that scale
        assert_close(torch.where(good, out.radiance[b], want), want, atol=TOL[F32] * max(1.0, 0.9 / sigma),
                     what=f"{mode} emissive radiance σ={sigma} ρ={density} scene {b}")


def test_constant_source_riemann_converges_first_order():
    sigma, density = 2.0, 1.0
    errors = []
    for n in (8, 16, 32, 64):
        keys = {"closed_form": False, "integrator": "riemann", "steps": n, "placement": "count", "dither": "none",
                "min_transmittance": 0.0}
        out = tv.render(_emissive_scenes(sigma, density, keys)[:1], dtype=F64)
        want, _, _ = _emissive_expected(out, 0, sigma, density)
        errors.append((out.radiance[0] - want).abs().max().item())
    orders = [math.log2(a / b) for a, b in zip(errors, errors[1:])]
    assert errors[-1] < 0.05 * 0.9 / sigma, f"riemann errors {errors}"
    assert all(0.8 < p < 1.25 for p in orders), f"riemann emissive orders {orders} (errors {errors}), expected ~1"


# ---------------------------------------------------------------------------------------------
# Exponential-density slab: closed-form optical depth, convergence order of the integrators

EXP = dict(value=1.0, base=-0.5, scale_height=0.4)
SLAB = (-0.5, 0.5)
EXP_SIGMA = 1.5


def _exp_scene(n, integrator):
    return {
        "image": {"width": 7, "height": 5},
        "camera": {"eye": [0.2, 2.0, -3.0], "target": [0.0, 0.0, 0.0], "fov_y": 30.0},
        "volumes": [{"bounds": {"slab": {"y_min": SLAB[0], "y_max": SLAB[1]}}, "density": {"exponential": EXP},
                     "sigma_t": EXP_SIGMA, "albedo": 0.0, "emission": [1.0, 1.0, 1.0]}],
        "march": {"integrator": integrator, "steps": n, "placement": "count", "dither": "none", "min_transmittance": 0.0},
    }


def _exp_expected(out):
    eye, dirs, _ = camera_rays(out, 0)
    t0, t1, hit = slab_interval(eye, dirs, *SLAB)
    assert hit.all() and (np.abs(dirs[..., 1]) > 0.3).all()
    H, dy = EXP["scale_height"], dirs[..., 1]
    y0, y1 = eye[1] + t0 * dy, eye[1] + t1 * dy
    # ∫ value·e^{−(y − base)/H} dt with y = o_y + t d_y
    tau = EXP_SIGMA * EXP["value"] * H / dy * (np.exp(-(y0 - EXP["base"]) / H) - np.exp(-(y1 - EXP["base"]) / H))
    alpha = -np.expm1(-tau)
    # emission E·ρ with extinction σρ: L = ∫ T E ρ dt = (E/σ)(1 − T)
    return alpha, alpha / EXP_SIGMA


@pytest.mark.parametrize("integrator", ["riemann", "frostbite"])
def test_exponential_slab_convergence_order(integrator):
    """Midpoint sampling: transmittance converges at order 2 for both integrators; emitted
    radiance at order 2 for frostbite (exact per segment up to the midpoint rule) and order 1 for
    riemann (S·Δt weighted by the transmittance at the segment's start)."""
    ns = (8, 16, 32, 64)
    ea, er = [], []
    for n in ns:
        out = tv.render(_exp_scene(n, integrator), dtype=F64)
        alpha, rad = _exp_expected(out)
        ea.append((out.alpha[0, 0].double() - torch.from_numpy(alpha)).abs().max().item())
        er.append((out.radiance[0].double() - torch.from_numpy(rad)[None]).abs().max().item())
    pa = [math.log2(a / b) for a, b in zip(ea, ea[1:])]
    pr = [math.log2(a / b) for a, b in zip(er, er[1:])]
    msg = f"{integrator}: alpha orders {np.round(pa, 3)} (errors {ea}); radiance orders {np.round(pr, 3)} (errors {er})"
    assert all(1.8 < p < 2.2 for p in pa), msg
    if integrator == "frostbite":
        assert all(1.8 < p < 2.2 for p in pr), msg
    else:
        assert all(0.8 < p < 1.25 for p in pr), msg
    assert ea[-1] < 1e-4, msg


# ---------------------------------------------------------------------------------------------
# Grid ramp: linear along x at the cell centres, clamp-to-edge in the half cells at the faces

GRID_LO, GRID_HI = np.array([-0.8, -0.5, -0.3]), np.array([0.8, 0.5, 0.5])
NI, NJ, NK = 4, 3, 2
RAMP_A, RAMP_B = 0.2, 0.6  # value at cell i: A + B·i


def _grid_data():
    vals = RAMP_A + RAMP_B * np.arange(NI, dtype=np.float64)
    return np.broadcast_to(vals[None, None, :], (NK, NJ, NI)).copy()  # [k, j, i]


def _ramp_antiderivative(x):
    """G(x) = ∫_{x_lo}^{x} ρ(s) ds for the clamped ramp ρ along x."""
    h = (GRID_HI[0] - GRID_LO[0]) / NI
    c0, c1 = GRID_LO[0] + 0.5 * h, GRID_HI[0] - 0.5 * h
    v0, v1 = RAMP_A, RAMP_A + RAMP_B * (NI - 1)
    slope = (v1 - v0) / (c1 - c0)
    x = np.clip(x, GRID_LO[0], GRID_HI[0])
    a = np.minimum(x, c0) - GRID_LO[0]
    m = np.clip(x, c0, c1) - c0
    z = np.maximum(x, c1) - c1
    return v0 * a + v0 * m + 0.5 * slope * m * m + v1 * z


def _ramp_value(x):
    h = (GRID_HI[0] - GRID_LO[0]) / NI
    c0, c1 = GRID_LO[0] + 0.5 * h, GRID_HI[0] - 0.5 * h
    return RAMP_A + RAMP_B * (NI - 1) * (np.clip(x, c0, c1) - c0) / (c1 - c0)


def _grid_tau(eye, dirs):
    t0, t1, hit = box_interval(eye, dirs, GRID_LO, GRID_HI)
    x0, x1 = eye[0] + t0 * dirs[..., 0], eye[0] + t1 * dirs[..., 0]
    dx = dirs[..., 0]
    flat = np.abs(x1 - x0) < 1e-12
    with np.errstate(divide="ignore", invalid="ignore"):
        tau = np.where(flat, _ramp_value(0.5 * (x0 + x1)) * (t1 - t0), (_ramp_antiderivative(x1) - _ramp_antiderivative(x0)) / dx)
    return np.where(hit, tau, 0.0)


@pytest.mark.parametrize("use_path", [False, True])
def test_grid_ramp_axis_aligned_rays(use_path, tmp_path):
    """Odd image sizes put the centre pixel's ray exactly along the view axis: an x-aligned ray
    crosses the whole ramp (clamped half cells at both faces), a y-aligned ray sees one value."""
    data = _grid_data()
    if use_path:
        np.save(tmp_path / "ramp.npy", data)
        density = {"grid": {"path": str(tmp_path / "ramp.npy")}}
    else:
        density = {"grid": {"data": data.tolist()}}
    bounds = {"box": {"min": GRID_LO.tolist(), "max": GRID_HI.tolist()}}
    sigma = 0.8
    # 2·NI·8 count steps put segment boundaries on the kinks at the half-cell points of the x ray
    keys = {"steps": 2 * NI * 8, "placement": "count", "dither": "none", "min_transmittance": 0.0}
    y0, z0 = 0.13, 0.07
    xs = [-0.75, -0.65, -0.3, 0.0, 0.45, 0.7, 0.79]  # includes points in the clamped half cells (|x| > 0.6)
    scenes = [scene([-3.0, y0, z0], [0.0, y0, z0], bounds, sigma=sigma, density=density, march=keys, width=9, height=7)]
    scenes += [scene([x, 2.5, z0], [x, 0.0, z0], bounds, sigma=sigma, density=density, march=keys, width=9, height=7) for x in xs]
    out = tv.render(scenes, dtype=F64)
    assert "volume0.march" in out.stats["passes"]
    want_x = sigma * (_ramp_antiderivative(GRID_HI[0]) - _ramp_antiderivative(GRID_LO[0]))
    got = out.alpha[:, 0, 3, 4].double()
    assert_close(got[0], torch.tensor(-math.expm1(-want_x), dtype=F64), atol=2e-7, what="x-aligned grid ray alpha")
    want_y = [-math.expm1(-sigma * _ramp_value(x) * (GRID_HI[1] - GRID_LO[1])) for x in xs]
    assert_close(got[1:], torch.tensor(want_y, dtype=F64), atol=2e-7, what=f"y-aligned grid ray alpha at x={xs}")


def test_grid_ramp_all_pixels():
    """Every ray (entering through any face) vs the piecewise-quadratic closed form."""
    bounds = {"box": {"min": GRID_LO.tolist(), "max": GRID_HI.tolist()}}
    keys = {"steps": 512, "placement": "count", "dither": "none", "min_transmittance": 0.0}
    mid = 0.5 * (GRID_LO + GRID_HI)
    views = [e for e in _around(mid, 2.6)]
    scenes = [scene(e, mid, bounds, sigma=1.3, density={"grid": {"data": _grid_data().tolist()}}, march=keys, width=10, height=8)
              for e in views]
    out = tv.render(scenes)  # float32
    for b in range(len(views)):
        eye, dirs, _ = camera_rays(out, b)
        fn = lambda e, d: -np.expm1(-1.3 * _grid_tau(e, d))
        good = well_conditioned(fn, eye, dirs, scale=3.0)
        assert good.mean() > 0.7
        want = torch.from_numpy(fn(eye, dirs)).float()
        assert_close(torch.where(torch.from_numpy(good), out.alpha[b, 0], want), want, atol=TOL[F32],
                     what=f"grid ramp alpha view {b}")


# ---------------------------------------------------------------------------------------------
# Expected termination depth and median depth


def _expected_t(t0, length, sigma):
    """E[t | terminated in [t0, t0 + L]] for a homogeneous medium, computed directly."""
    x = sigma * length
    with np.errstate(divide="ignore", invalid="ignore"):
        # ∫0^L s σ e^{−σs} ds / (1 − e^{−σL}) = (1 − (1 + x) e^{−x}) / (σ (1 − e^{−x}))
        frac = (-np.expm1(-x) - x * np.exp(-x)) / (sigma * -np.expm1(-x))
    frac = np.where(x < 1e-6, 0.5 * length, frac)
    return t0 + frac


@pytest.mark.parametrize("kind", ["sphere", "slab"])
@pytest.mark.parametrize("mode", ["closed_form", "march"])
def test_expected_and_median_depth(kind, mode):
    sigmas = [0.3, 2.0, 15.0, 200.0]
    if kind == "sphere":
        bounds = _bounds("sphere")
        views = [(e, CENTER) for e in _around(CENTER, 3.5)[:3]] + [(CENTER + [0.2, 0.1, -0.3], CENTER + [1.0, 0.3, 2.0])]
        interval = lambda e, d: sphere_interval(e, d, CENTER, RADIUS)
    else:
        bounds = {"slab": {"y_min": -0.5, "y_max": 0.25}}
        views = [([0.1, 2.0, -2.0], [0.0, 0.0, 0.5]), ([0.0, -2.0, -1.0], [0.3, 0.0, 0.0]), ([0.0, 0.0, -1.0], [0.4, -0.6, 1.0])]
        interval = lambda e, d: slab_interval(e, d, -0.5, 0.25)
    steps = 48
    keys = None if mode == "closed_form" else {"closed_form": False, "steps": steps, "dither": "none", "min_transmittance": 0.0}
    scenes = [scene(e, t, bounds, sigma=s, march=keys, fov=40.0) for e, t in views for s in sigmas]
    out = tv.render(scenes)
    threshold = 0.01
    for b, (view, sigma) in enumerate((v, s) for v in views for s in sigmas):
        eye, dirs, fcos = camera_rays(out, b)

        def fields(e, d, sigma=sigma):
            t0, t1, hit = interval(e, d)
            alpha = -np.expm1(-sigma * (t1 - t0))
            depth = np.where(hit & (alpha >= threshold), _expected_t(t0, t1 - t0, sigma), 0.0)
            median = np.where(hit & (alpha > 0.5), t0 + LN2 / sigma, 0.0)
            return alpha, depth, median

        alpha, depth, median = fields(eye, dirs)
        scale = 1.0 + np.abs(depth).max()
        good = np.ones(alpha.shape, bool)
        for k in range(3):
            good &= well_conditioned(lambda e, d, k=k: fields(e, d)[k] / (1 if k == 0 else scale), eye, dirs, scale=4.0)
        # stay away from the depth threshold and the median's alpha = 0.5 switch
        good &= (np.abs(alpha - threshold) > 1e-3) & (np.abs(alpha - 0.5) > 1e-3)
        assert good.mean() > 0.6, f"view {b}: {good.mean():.0%} well conditioned"
        g = torch.from_numpy(good)

        def check(got, want, atol, what):
            """Per-pixel tolerance `atol` [H, W]: compare the error in units of it."""
            err = (got.double() - torch.from_numpy(want)) / torch.from_numpy(atol)
            assert_close(torch.where(g, err, torch.zeros_like(err)), 0.0, atol=1.0,
                         what=f"{kind} {mode} {what} view {b} σ={sigma} (error / tolerance)")

        t0, t1, _ = interval(eye, dirs)
        tol = np.full(alpha.shape, 2e-5 * scale)
        if mode == "march":
            # the march weights each segment at its midpoint (DESIGN: Σ wᵢ zᵢ / Σ wᵢ); inside a
            # segment of optical depth x the exact conditional mean is Δt(1/x − 1/(eˣ − 1)) ≈
            # Δt(1/2 − x/12): a bias of at most σΔt²/12 per segment
            dt = (t1 - t0) / steps
            tol = tol + 1.05 * sigma * dt * dt / 12.0
        check(out.depth[b, 0], depth * fcos, tol, "expected depth")
        check(out.aovs["distance"][b, 0], depth, tol, "distance")
        check(out.aovs["depth_median"][b, 0], median * fcos, np.full(alpha.shape, 2e-5 * scale), "median depth")


# ---------------------------------------------------------------------------------------------
# Single scattering of a sun in a homogeneous slab: unshadowed and shadowed, closed forms


def _hg(cos, g):
    return (1 - g * g) / (4 * math.pi * (1 + g * g - 2 * g * cos) ** 1.5)


SUN_DIR = np.array([0.3, 1.0, -0.2]) / np.linalg.norm([0.3, 1.0, -0.2])
SUN_RGB = np.array([1.0, 0.8, 0.5]) * 1.7


def _sun_scene(sigma, g, *, shadow, march_keys=None):
    light = {"kind": "sun", "direction": SUN_DIR.tolist(), "color": [1.0, 0.8, 0.5], "intensity": 1.7}
    if shadow:
        light["shadow"] = {"steps": 4}
    s = scene([0.3, 2.0, -2.5], [0.0, 0.0, 0.0], {"slab": {"y_min": -0.5, "y_max": 0.5}}, sigma=sigma, width=9, height=7,
              fov=40.0, march=march_keys, albedo=0.8, phase={"hg": {"g": g}})
    s["volumes"][0]["albedo"] = 0.8
    s["lights"] = [light]
    return s


@pytest.mark.parametrize("g", [0.0, 0.6, -0.4])
@pytest.mark.parametrize("mode", ["closed_form", "march"])
def test_single_scattering_unshadowed(g, mode):
    """L = albedo · p(d·sun) · E · (1 − e^{−σ d}) for a homogeneous medium and an unshadowed sun."""
    sigma = 1.3
    keys = None if mode == "closed_form" else {"closed_form": False, "steps": 5, "dither": "none"}
    out = tv.render(_sun_scene(sigma, g, shadow=False, march_keys=keys))
    assert out.stats["passes"][1] == f"volume0.{mode}"
    eye, dirs, _ = camera_rays(out, 0)
    t0, t1, _ = slab_interval(eye, dirs, -0.5, 0.5)
    p = _hg(dirs @ SUN_DIR, g)
    want = 0.8 * SUN_RGB[:, None, None] * (p * -np.expm1(-sigma * (t1 - t0)))[None]
    assert_close(out.radiance[0], torch.from_numpy(want).float(), what=f"single scattering g={g} {mode}")


@pytest.mark.parametrize("g", [0.0, 0.6])
def test_single_scattering_shadowed_slab(g):
    """With the sun's shadow through the slab (exit along the sun direction at (y_max − y)/sun_y),
    the integrand is exponential in t: L = σs p E e^{−σ(y_max − o_y)/s_y} e^{σ t0} (e^{−a t0} − e^{−a t1}) / a,
    a = σ(1 − d_y/s_y). The homogeneous shadow march is exact; the view march converges at order 2."""
    sigma = 1.3
    keys = {"steps": 128, "dither": "none", "min_transmittance": 0.0}
    out = tv.render(_sun_scene(sigma, g, shadow=True, march_keys=keys), dtype=F64)
    assert "volume0.shadow0" in out.stats["passes"]
    eye, dirs, _ = camera_rays(out, 0)
    t0, t1, hit = slab_interval(eye, dirs, -0.5, 0.5)
    assert hit.all()
    dy, sy = dirs[..., 1], SUN_DIR[1]
    a = sigma * (1 - dy / sy)
    integral = np.exp(-sigma * (0.5 - eye[1]) / sy + sigma * t0) * (np.exp(-a * t0) - np.exp(-a * t1)) / a
    want = 0.8 * sigma * SUN_RGB[:, None, None] * (_hg(dirs @ SUN_DIR, g) * integral)[None]
    assert_close(out.radiance[0].double(), torch.from_numpy(want), atol=2e-5, what=f"shadowed single scattering g={g}")


# ---------------------------------------------------------------------------------------------
# Two volumes: transmittances multiply; the expected depth combines them front to back

TWO_BOX = ([-0.9, -0.5, -0.5], [-0.1, 0.5, 0.5])
TWO_SPHERE = ([0.45, 0.1, 0.2], 0.5)


def _two_volume_scene(march_keys, overlap=False):
    box_hi = [0.5, 0.5, 0.5] if overlap else TWO_BOX[1]
    return {
        "image": {"width": 11, "height": 7},
        "camera": {"eye": [0.2, 0.7, -3.0], "target": [0.0, 0.0, 0.0], "fov_y": 45.0},
        "volumes": [
            {"bounds": {"box": {"min": TWO_BOX[0], "max": box_hi}}, "density": {"constant": 1.0}, "sigma_t": 1.5, "albedo": 0.0},
            {"bounds": {"sphere": {"center": TWO_SPHERE[0], "radius": TWO_SPHERE[1]}}, "density": {"constant": 1.0},
             "sigma_t": 4.0, "albedo": 0.0},
        ],
        "march": march_keys,
    }


@pytest.mark.parametrize("overlap", [False, True])
@pytest.mark.parametrize("mode", ["closed_form", "march"])
def test_two_volumes_alpha(mode, overlap):
    keys = {"closed_form": mode == "closed_form", "steps": 8}
    out = tv.render(_two_volume_scene(keys, overlap))
    eye, dirs, _ = camera_rays(out, 0)
    box_hi = [0.5, 0.5, 0.5] if overlap else TWO_BOX[1]
    fn = lambda e, d: -np.expm1(-1.5 * np.subtract(*box_interval(e, d, TWO_BOX[0], box_hi)[1::-1])
                                - 4.0 * np.subtract(*sphere_interval(e, d, *TWO_SPHERE)[1::-1]))
    good = torch.from_numpy(well_conditioned(fn, eye, dirs, scale=3.0))
    want = torch.from_numpy(fn(eye, dirs)).float()
    assert_close(torch.where(good, out.alpha[0, 0], want), want, what=f"two volumes {mode} overlap={overlap} alpha")


def _two_volume_depth_expected(eye, dirs):
    a0, a1, ah = box_interval(eye, dirs, *TWO_BOX)
    b0, b1, bh = sphere_interval(eye, dirs, *TWO_SPHERE)
    aa, ab = -np.expm1(-1.5 * (a1 - a0)), -np.expm1(-4.0 * (b1 - b0))
    ea, eb = _expected_t(a0, a1 - a0, 1.5), _expected_t(b0, b1 - b0, 4.0)
    box_first = ~bh | (ah & (a0 <= b0))
    ta = np.where(box_first, 1.0, 1.0 - ab)  # transmittance in front of each volume
    tb = np.where(box_first, 1.0 - aa, 1.0)
    wsum = ta * aa + tb * ab
    with np.errstate(invalid="ignore", divide="ignore"):
        dist = np.where(wsum > 0, (ta * aa * np.where(ah, ea, 0) + tb * ab * np.where(bh, eb, 0)) / wsum, 0.0)
    alpha = 1 - (1 - aa) * (1 - ab)
    return np.where(alpha >= 0.01, dist, 0.0), alpha


@pytest.mark.parametrize("mode", [
    "closed_form",
    "march",
])
def test_two_volumes_expected_depth(mode):
    keys = {"closed_form": mode == "closed_form", "steps": 64, "dither": "none", "min_transmittance": 0.0}
    out = tv.render(_two_volume_scene(keys))
    eye, dirs, fcos = camera_rays(out, 0)
    dist, alpha = _two_volume_depth_expected(eye, dirs)
    assert torch.isfinite(out.depth).all() and torch.isfinite(out.aovs["distance"]).all(), "non-finite depth"
    good = well_conditioned(lambda e, d: _two_volume_depth_expected(e, d)[0] / 4.0, eye, dirs, scale=3.0)
    good &= np.abs(alpha - 0.01) > 1e-3
    g = torch.from_numpy(good)
    # march: midpoint weighting bias ≤ σΔt²/12 per segment (Δt ≤ 1.2/64 here)
    atol = 1e-4 if mode == "closed_form" else 1e-4 + 4.0 * (1.2 / 64) ** 2 / 12
    want = torch.from_numpy(dist * fcos).float()
    assert_close(torch.where(g, out.depth[0, 0], want), want, atol=atol, what=f"two volumes {mode} depth")
