"""Hard cases: extreme extinction, rays parallel to slab planes and axes, cameras inside volumes
and exactly on their bounds, near-singular phase functions, both dtypes. Nothing may come out
non-finite or out of range; transmittance never grows along a ray; radiance respects energy
bounds; bad input is refused with a ValueError naming the key."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import TOL, assert_close
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import torchvol as tv
from torchvol.volume.march import StepRule, march

SIGMAS = [0.0, 1e-12, 1e-3, 1e3, 1e7]
FAST = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True)

BOUNDS = {
    "box": {"box": {"min": [-0.5, -0.5, -0.5], "max": [0.5, 0.5, 0.5]}},
    "sphere": {"sphere": {"center": [0.0, 0.0, 0.0], "radius": 0.5}},
    "slab": {"slab": {"y_min": -0.5, "y_max": 0.5}},
    "shell": {"shell": {"planet_radius": 1.0, "bottom": 0.0, "top": 0.5}},  # its ground through the origin
}

# (eye, target, up): outside, on axes looking along them (odd image sizes put the centre ray
# exactly on the axis, with zero direction components), inside, exactly on faces / edges /
# corners / the sphere, and looking along the slab planes (a row of rays with d.y == 0 exactly).
VIEWS = [
    ([1.2, 0.9, -2.0], [0.0, 0.0, 0.0], [0, 1, 0]),
    ([0.0, 0.0, -3.0], [0.0, 0.0, 0.0], [0, 1, 0]),
    ([3.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0, 1, 0]),
    ([0.0, 3.0, 0.0], [0.0, 0.0, 0.0], [0, 0, 1]),
    ([0.0, -3.0, 0.0], [0.0, 0.0, 0.0], [1, 0, 0]),
    ([0.1, -0.2, 0.05], [1.0, 0.3, 2.0], [0, 1, 0]),
    ([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0, 1, 0]),
    ([0.0, 0.0, -0.5], [0.0, 0.0, 0.0], [0, 1, 0]),  # on the box face / the sphere
    ([0.0, 0.0, -0.5], [0.0, 0.0, -2.0], [0, 1, 0]),  # on the boundary looking out
    ([0.5, 0.5, 0.0], [0.0, 0.0, 0.0], [0, 0, 1]),  # on a box edge
    ([-0.5, -0.5, -0.5], [0.5, 0.5, 0.5], [0, 1, 0]),  # on a box corner, along the diagonal
    ([0.0, 0.5, -2.0], [0.0, 0.5, 0.0], [0, 1, 0]),  # in the slab's top plane, looking along it
    ([0.0, 0.0, -2.0], [0.3, 0.0, 1.0], [0, 1, 0]),  # inside the slab, horizontal
    ([0.0, 0.5, 0.0], [1.0, 0.5, 0.0], [0, 1, 0]),  # on the top plane (and the sphere's pole)
]

PHASES = [
    "isotropic",
    {"hg": {"g": 0.999}},
    {"hg": {"g": -0.999}},
    {"dual_hg": {"g_forward": 0.999, "g_backward": -0.999, "weight": 0.5}},
    {"mie": {"g": 0.999}},
    "rayleigh",
]

DENSITIES = [
    {"constant": 1.0},
    {"constant": 1e-9},
    {"exponential": {"value": 2.0, "base": -0.5, "scale_height": 0.05}},
    {"fbm": {"octaves": 2, "frequency": 3.0, "bias": 0.2}},
    {"grid": {"data": [[[0.0, 3.0], [1.0, 0.0]], [[0.5, 2.0], [0.0, 4.0]]]}},
    {"cloudscape": {"bottom": -0.5, "top": 0.5, "coverage": 0.9, "scale": 1.0, "detail_scale": 0.3}},
]


@st.composite
def scenes(draw, *, sky=None, lights=None):
    kind = draw(st.sampled_from(sorted(BOUNDS)))
    eye, target, up = draw(st.sampled_from(VIEWS))
    density = draw(st.sampled_from(DENSITIES))
    if "grid" in density and kind != "box":
        density = {"constant": 1.0}
    vol = {
        "bounds": BOUNDS[kind],
        "density": density,
        "sigma_t": draw(st.sampled_from(SIGMAS)),
        "albedo": draw(st.sampled_from([0.0, 0.5, 1.0])),
        "phase": draw(st.sampled_from(PHASES)),
    }
    if draw(st.booleans()):
        vol["emission"] = [0.3, 0.0, 1.0]
    if lights is None:
        lights = draw(st.sampled_from([
            [],
            [{"direction": [0.0, 0.0, -1.0], "intensity": 2.0}],  # towards the camera: the HG peak
            [{"direction": [1.0, 1.0, -0.5], "shadow": {"steps": 4}}],
            [{"direction": [0.0, 1.0, 0.0], "shadow": {"steps": 3, "growth": 2.0}}, {"direction": [0.0, 0.0, 1.0]}],
            # point lights: on the bounds' centre (rays pass through the light), outside, shadowed
            [{"kind": "point", "position": [0.0, 0.0, 0.0], "intensity": 5.0, "shadow": {"steps": 3}}],
            [{"kind": "point", "position": [0.0, 3.0, 0.0], "intensity": 20.0}, {"direction": [1.0, 1.0, -0.5]}],
        ]))
    s = {
        "image": {"width": draw(st.sampled_from([7, 8])), "height": draw(st.sampled_from([5, 8]))},
        "camera": {"eye": eye, "target": target, "up": up, "fov_y": draw(st.sampled_from([1.0, 40.0, 170.0]))},
        "volumes": [vol],
        "lights": lights,
        "march": {
            "quality": "draft",
            "closed_form": draw(st.booleans()),
            "integrator": draw(st.sampled_from(["riemann", "frostbite"])),
            "steps": draw(st.sampled_from([1, 3, 16])),
            "dither": draw(st.sampled_from(["none", "hash", "sin"])),
        },
    }
    if sky is not None:
        s["sky"] = sky
    elif draw(st.booleans()):
        s["sky"] = draw(st.sampled_from([{"kind": "constant", "radiance": [1.0, 1.0, 1.0]}, {"kind": "gradient"}]))
    return s


def check_output(out, what=""):
    for name in ("image", "radiance", "depth", "alpha"):
        x = getattr(out, name)
        assert x.dtype == torch.float32, f"{what} {name} dtype {x.dtype}"
        assert torch.isfinite(x).all(), f"{what} {name} has non-finite values at {(~torch.isfinite(x)).nonzero()[:3].tolist()}"
    for name, x in out.aovs.items():
        assert torch.isfinite(x).all(), f"{what} aov {name} has non-finite values"
        assert (x >= 0).all(), f"{what} aov {name} negative: {x.min().item()}"
    assert (out.alpha >= 0).all() and (out.alpha <= 1).all(), f"{what} alpha in [{out.alpha.min()}, {out.alpha.max()}]"
    assert (out.image >= 0).all() and (out.image <= 1).all(), f"{what} image out of [0, 1]"
    assert (out.radiance >= 0).all(), f"{what} negative radiance {out.radiance.min().item()}"
    assert (out.depth >= 0).all(), f"{what} negative depth {out.depth.min().item()}"
    # depth is reported exactly where alpha reaches the threshold (0.01 by default)
    assert ((out.depth > 0) <= (out.alpha >= 0.01 - 1e-6)).all(), f"{what} depth where alpha < threshold"


@FAST
@given(scene=scenes(), dtype=st.sampled_from([torch.float32, torch.float64]))
def test_no_nan_no_out_of_range(scene, dtype):
    out = tv.render(scene, dtype=dtype)
    check_output(out, what=f"{dtype} {scene}")


@FAST
@given(scene=scenes(sky={"kind": "constant", "radiance": [1.0, 1.0, 1.0]}, lights=[]),
       dtype=st.sampled_from([torch.float32, torch.float64]))
def test_energy_bound_unit_sky_no_sun(scene, dtype):
    """No sun, no emission, a unit sky: only transmitted sky arrives, radiance ≤ 1."""
    scene["volumes"][0].pop("emission", None)
    out = tv.render(scene, dtype=dtype)
    check_output(out)
    assert out.radiance.max() <= 1.0 + TOL[torch.float32], f"radiance {out.radiance.max().item()} > 1"
    # and it is exactly the transmitted sky: radiance = 1 − alpha
    assert_close(out.radiance, (1.0 - out.alpha).expand_as(out.radiance), atol=TOL[torch.float32], what="transmitted sky")


@FAST
@given(sigma=st.sampled_from(SIGMAS[1:] + [0.5, 5.0]), albedo=st.sampled_from([0.3, 1.0]),
       closed=st.booleans(), kind=st.sampled_from(sorted(BOUNDS)), view=st.sampled_from(VIEWS[:8]))
def test_energy_bound_single_scattering_isotropic(sigma, albedo, closed, kind, view):
    """Isotropic single scattering of a unit sun, no shadow: L = ∫ T σs p E dt ≤ albedo·(1/4π)·alpha."""
    eye, target, up = view
    scene = {
        "image": {"width": 7, "height": 5},
        "camera": {"eye": eye, "target": target, "up": up, "fov_y": 60.0},
        "volumes": [{"bounds": BOUNDS[kind], "density": {"constant": 1.0}, "sigma_t": sigma, "albedo": albedo}],
        "lights": [{"direction": [0.3, 1.0, -0.2], "intensity": 1.0}],
        "march": {"quality": "draft", "closed_form": closed, "dither": "none"},
    }
    out = tv.render(scene)
    check_output(out)
    bound = albedo / (4 * math.pi) * out.alpha
    assert (out.radiance <= bound + 1e-6).all(), f"radiance exceeds albedo·p·alpha by {(out.radiance - bound).max().item()}"


# ---------------------------------------------------------------------------------------------
# Transmittance along a ray (functional core)


def bumpy_medium(centers, widths, heights, recorder=None):
    c, w, h = (torch.tensor(x, dtype=torch.float64) for x in (centers, widths, heights))

    def medium(ids, t, dt):
        sigma = (h * torch.exp(-(((t[:, None] - c) / w) ** 2))).sum(dim=1)
        if recorder is not None:
            recorder.append((ids.clone(), t.clone(), dt.clone(), sigma.clone()))
        return sigma, torch.ones(t.shape[0], 3, dtype=t.dtype) * sigma[:, None]

    return medium


bumps = st.lists(st.tuples(st.floats(0.0, 4.0), st.floats(0.01, 1.0), st.floats(0.0, 50.0)), min_size=1, max_size=4)


@FAST
@given(bumps=bumps, n=st.integers(1, 40), integrator=st.sampled_from(["riemann", "frostbite"]),
       dither=st.booleans(), placement=st.sampled_from(["count", "size", "adaptive"]))
def test_transmittance_monotone_along_ray(bumps, n, integrator, dither, placement):
    c, w, h = map(list, zip(*bumps))
    R = 6
    t0 = torch.linspace(0.0, 1.0, R, dtype=torch.float64)
    t1 = t0 + torch.linspace(0.5, 4.0, R, dtype=torch.float64)
    hit = torch.ones(R, dtype=torch.bool)
    rec = []
    rule = StepRule(placement, n if placement == "count" else 10_000, step_size=4.0 / n, step_growth=0.05)
    d = torch.linspace(0.05, 0.95, R, dtype=torch.float64) if dither else None
    res = march(t0, t1, hit, bumpy_medium(c, w, h, rec), rule=rule, integrator=integrator, dither=d)
    # rebuild each ray's transmittance step by step from what the march asked the medium
    T = torch.ones(R, dtype=torch.float64)
    covered = torch.zeros(R, dtype=torch.float64)
    for ids, t, dt, sigma in rec:
        assert (dt >= 0).all() and (sigma >= 0).all()
        new = T[ids] * torch.exp(-sigma * dt)
        assert (new <= T[ids]).all(), "transmittance grew along a ray"
        T[ids] = new
        covered[ids] += dt
    assert_close(res.transmittance, T, atol=1e-12, what="march transmittance vs product of its segments")
    assert_close(covered, t1 - t0, atol=1e-9, what="segments cover [t0, t1] exactly")
    # weights telescope: Σ T_i (1 − t_i) = 1 − T
    assert_close(res.weight_sum, 1.0 - res.transmittance, atol=1e-12, what="Σw = alpha")
    assert (res.radiance >= 0).all() and torch.isfinite(res.radiance).all()


@FAST
@given(bumps=bumps, k=st.integers(1, 12), integrator=st.sampled_from(["riemann", "frostbite"]))
def test_truncated_marches_never_gain_transmittance(bumps, k, integrator):
    """Fixed-size steps: marching to t0 + j·h shares its segments with longer marches, so T(j) is
    non-increasing in j and radiance (non-negative source) non-decreasing."""
    c, w, h = map(list, zip(*bumps))
    step = 0.3
    ends = torch.arange(1, k + 1, dtype=torch.float64) * step
    t0 = torch.zeros(k, dtype=torch.float64)
    res = march(t0, ends, torch.ones(k, dtype=torch.bool), bumpy_medium(c, w, h), rule=StepRule("size", 1000, step_size=step),
                integrator=integrator)
    T = res.transmittance
    assert (T[1:] <= T[:-1]).all(), f"transmittance not monotone: {T.tolist()}"
    assert (res.radiance[1:] >= res.radiance[:-1] - 1e-15).all()


@FAST
@given(bumps=bumps, min_t=st.sampled_from([1e-1, 1e-2, 1e-4]))
def test_early_termination_only_stops_below_threshold(bumps, min_t):
    c, w, h = map(list, zip(*bumps))
    R = 5
    t0 = torch.zeros(R, dtype=torch.float64)
    t1 = torch.linspace(1.0, 4.0, R, dtype=torch.float64)
    hit = torch.ones(R, dtype=torch.bool)
    rule = StepRule("count", 32)
    full = march(t0, t1, hit, bumpy_medium(c, w, h), rule=rule, integrator="frostbite")
    early = march(t0, t1, hit, bumpy_medium(c, w, h), rule=rule, integrator="frostbite", min_transmittance=min_t)
    assert (early.transmittance >= full.transmittance).all()
    stopped = early.transmittance != full.transmittance
    assert (early.transmittance[stopped] < min_t).all()
    assert (full.transmittance[stopped] < min_t).all()
    assert (early.transmittance - full.transmittance <= min_t).all()


# ---------------------------------------------------------------------------------------------
# Bad input: ValueError naming the key


def good_scene():
    return {
        "image": {"width": 8, "height": 8},
        "camera": {"eye": [0.0, 0.0, -3.0], "target": [0.0, 0.0, 0.0], "fov_y": 40.0},
        "volumes": [{"bounds": {"box": {"min": [-0.5, -0.5, -0.5], "max": [0.5, 0.5, 0.5]}}, "density": {"constant": 1.0},
                     "sigma_t": 2.0}],
        "lights": [{"kind": "sun", "direction": [1.0, 1.0, 0.0]}],
    }


BAD = [
    ("volumes[0].sigma_t", -1.0, "volumes[0].sigma_t"),
    ("volumes[0].sigma_t", float("nan"), "volumes[0].sigma_t"),
    ("volumes[0].sigma_t", float("inf"), "volumes[0].sigma_t"),
    ("volumes[0].albedo", 1.5, "volumes[0].albedo"),
    ("volumes[0].density", {"constant": -2.0}, "volumes[0].density.constant"),
    ("volumes[0].density", {"constant": float("nan")}, "volumes[0].density.constant"),
    ("volumes[0].emission", [0.0, -1.0, 0.0], "volumes[0].emission"),
    ("image.width", 0, "image.width"),
    ("image.height", 0, "image.height"),
    ("image.width", -4, "image.width"),
    ("image.spp", 0, "image.spp"),
    ("camera.fov_y", 0.0, "camera.fov_y"),
    ("camera.fov_y", 180.0, "camera.fov_y"),
    ("camera.fov_y", float("nan"), "camera.fov_y"),
    ("camera.eye", [0.0, 0.0, 0.0], "camera"),  # == target
    ("camera.up", [0.0, 0.0, 1.0], "camera"),  # parallel to the view direction
    ("camera.eyes", [1.0, 2.0, 3.0], "camera.eyes"),
    ("volumes[0].sigmat", 1.0, "volumes[0].sigmat"),
    ("foo", 1, "foo"),
    ("image.width", "wide", "image.width"),
    ("image.width", 8.5, "image.width"),
    ("camera.eye", "here", "camera.eye"),
    ("camera.eye", [1.0, 2.0], "camera.eye"),
    ("volumes[0].sigma_t", "thick", "volumes[0].sigma_t"),
    ("volumes[0].density", {"grid": {"path": "/nonexistent/missing-grid.npy"}}, "volumes[0].density.grid"),
    ("volumes[0].density", {"grid": {"data": [[[1.0, float("nan")]]]}}, "volumes[0].density.grid"),
    ("volumes[0].density", {"grid": {"data": [1.0, 2.0]}}, "volumes[0].density.grid"),
    ("volumes[0].bounds", {"sphere": {"radius": 0.0}}, "volumes[0].bounds.sphere.radius"),
    ("volumes[0].bounds", {"box": {"min": [0, 0, 0], "max": [1, 0, 1]}}, "volumes[0].bounds.box"),
    ("volumes[0].bounds", {"slab": {"y_min": 1.0, "y_max": 1.0}}, "volumes[0].bounds.slab"),
    ("volumes[0].phase", {"hg": {"g": 1.0}}, "volumes[0].phase.hg.g"),
    ("lights[0].direction", [0.0, 0.0, 0.0], "lights[0].direction"),
    ("lights[0].intensity", -1.0, "lights[0].intensity"),
    ("lights[0].kind", "spot", "lights[0].kind"),
    ("march.quality", "ultra", "march.quality"),
    ("march.steps", 0, "march.steps"),
    ("march.integrator", "simpson", "march.integrator"),
    ("march.min_transmittance", 1.0, "march.min_transmittance"),
]


@pytest.mark.parametrize("key,value,path", BAD, ids=[f"{k}={v!r}"[:48] for k, v, _ in BAD])
def test_bad_input_refused_naming_key(key, value, path):
    with pytest.raises(ValueError) as exc:
        tv.render(tv.load_scene(good_scene(), overrides={key: value}))
    msg = str(exc.value)
    assert msg.startswith(path), f"message does not start with the key path {path!r}: {msg}"


def test_bad_render_arguments():
    for kwargs, name in [({"seed": 1.5}, "seed"), ({"chunk_rays": 0}, "chunk_rays")]:
        with pytest.raises(ValueError, match=name):
            tv.render(good_scene(), **kwargs)
    with pytest.raises(ValueError):
        tv.render([])
    other = good_scene()
    other["volumes"][0]["density"] = {"fbm": {}}
    with pytest.raises(ValueError, match=r"scenes\[1\]"):
        tv.render([good_scene(), other])


def test_bad_input_from_dict_without_overrides():
    s = good_scene()
    s["volumes"][0]["sigma_t"] = -3.0
    with pytest.raises(ValueError, match=r"volumes\[0\]\.sigma_t"):
        tv.render(s)


@pytest.mark.parametrize("sigma", [3.0, 1e3])
def test_alpha_integrator_physical_shading_in_range(sigma):
    s = good_scene()
    s["volumes"][0]["sigma_t"] = sigma
    s["march"] = {"integrator": "alpha", "steps": 4, "dither": "none"}
    try:
        out = tv.render(s)
    except ValueError as exc:  # refusing the combination, naming the key, is also correct
        assert "march.integrator" in str(exc) or "shading" in str(exc)
        return
    check_output(out, what=f"alpha integrator σ={sigma}")


@FAST
@given(bumps=bumps, compact_below=st.sampled_from([0.0, 0.5, 0.75]), semantics=st.sampled_from(["segments", "shader"]),
       min_t=st.sampled_from([0.0, 1e-2]), limit=st.sampled_from([12, 1000]))
def test_when_the_march_compacts_does_not_change_its_result(bumps, compact_below, semantics, min_t, limit):
    """Finished rays kept in the batch (zero-length steps) until it compacts give what compacting
    after every step gives: radiance, transmittance, weights, median, step counts, truncation."""
    c, w, h = map(list, zip(*bumps))
    R = 7
    t0 = torch.linspace(0.0, 1.0, R, dtype=torch.float64)
    t1 = t0 + torch.linspace(0.2, 4.0, R, dtype=torch.float64)
    hit = torch.ones(R, dtype=torch.bool)
    hit[3] = False
    rule = StepRule("size", limit, step_size=0.25)
    dither = torch.linspace(0.1, 0.9, R, dtype=torch.float64)
    bumpy = bumpy_medium(c, w, h)

    def medium(ids, t, dt):  # the shader semantics wants opacities
        sigma, source = bumpy(ids, t, dt)
        return ((sigma * 0.05).clamp(max=1.0), source) if semantics == "shader" else (sigma, source)

    runs = [march(t0, t1, hit, medium, rule=rule, integrator="frostbite", semantics=semantics, dither=dither,
                  min_transmittance=min_t, compact_below=cb) for cb in (1.0, compact_below)]
    for name in ("radiance", "transmittance", "weight_sum", "weighted_t", "median_t"):
        assert_close(getattr(runs[1], name), getattr(runs[0], name), atol=1e-12, what=name)
    assert torch.equal(runs[1].steps, runs[0].steps) and torch.equal(runs[1].truncated, runs[0].truncated)


# -- the wave-2 techniques' hard cases, each over its whole parameter range -----------------------

SUN = {"kind": "sun", "direction": [0.3, 1.0, -0.2], "shadow": {"steps": 4}}


def _small(**extra):
    return {"image": {"width": 7, "height": 5}, "march": {"steps": 8}, **extra}


@FAST
@given(value=st.one_of(st.just(0.0), st.floats(1e-6, 1e12)), base=st.floats(-50.0, 50.0),
       scale_height=st.floats(1e-6, 1e3), sigma_t=st.one_of(st.just(0.0), st.floats(1e-6, 1e12)),
       bounds=st.sampled_from(sorted(BOUNDS)), eye_y=st.floats(-3.0, 3.0), dtype=st.sampled_from([torch.float32, torch.float64]))
def test_exponential_densities_never_overflow(value, base, scale_height, sigma_t, bounds, eye_y, dtype):
    """Far below its base a small scale height would give e^{1000} (inf, and inf × 0 NaN): the
    density is capped, so images, alpha and depth stay finite and in range, cameras inside too."""
    scene = _small(camera={"eye": [0.0, eye_y, -2.0], "target": [0.0, 0.0, 0.0]}, lights=[SUN],
                   sky={"kind": "constant", "radiance": [0.2, 0.3, 0.4]},
                   volumes=[{"bounds": BOUNDS[bounds], "sigma_t": sigma_t, "albedo": 0.8,
                             "density": {"exponential": {"value": value, "base": base, "scale_height": scale_height}}}])
    check_output(tv.render(scene, dtype=dtype), what=f"{dtype} {scene}")


@FAST
@given(shading=st.sampled_from(["physical", "shader", "surface"]), fog=st.floats(0.0, 10.0),
       bounds=st.sampled_from(sorted(BOUNDS)), compile=st.sampled_from(["off", "kernels"]))
def test_every_shading_renders_without_a_sky(shading, fog, bounds, compile):
    """No [sky]: black behind, for every shading (the shader look's fog blends towards it)."""
    volume = {"bounds": BOUNDS[bounds], "density": {"clouds": {}}, "shading": shading}
    if shading == "shader":
        volume["shader"] = {"fog": fog}
    scene = _small(camera={"eye": [0.0, 0.2, -2.0], "target": [0.0, 0.0, 0.0]}, lights=[SUN], volumes=[volume])
    check_output(tv.render(scene, compile=compile), what=str(scene))


@FAST
@given(eye_y=st.floats(-5.0, 5.0), base=st.floats(-2.0, 2.0), amplitude=st.floats(0.0, 3.0),
       pitch=st.floats(-1.0, 1.0))
def test_cameras_under_the_terrain_see_the_ground_at_zero(eye_y, base, amplitude, pitch):
    """The ground is solid: a camera under the surface meets it at once (alpha 1, depth 0, never
    negative); above it, depth is positive where the terrain is hit."""
    scene = _small(camera={"eye": [0.0, eye_y, -3.0], "target": [0.0, eye_y + pitch, 3.0]}, lights=[SUN],
                   terrain={"base": base, "amplitude": amplitude, "steps": 32})
    out = tv.render(scene)
    for name, x in [("image", out.image), ("depth", out.depth), ("alpha", out.alpha), *out.aovs.items()]:
        assert torch.isfinite(x).all(), f"{scene}: {name} has non-finite values"
    assert (out.depth >= 0).all(), f"{scene}: negative depth {out.depth.min().item()}"
    assert (out.alpha >= 0).all() and (out.alpha <= 1).all() and (out.image >= 0).all() and (out.image <= 1).all()
    under = eye_y < base - amplitude - 1e-3
    if under:
        assert (out.alpha == 1).all() and (out.depth == 0).all(), f"{scene}: a camera in the ground sees past it"


# -- found by the fuzz (torchvol.measure.fuzz, tests/test_fuzz.py) ---------------------------------


@FAST
@given(horizon=st.tuples(*[st.floats(0.0, 1.0)] * 3), slope=st.tuples(*[st.floats(-2.0, 2.0)] * 3),
       pitch=st.floats(-3.0, 3.0))
def test_gradient_sky_is_never_negative(horizon, slope, pitch):
    """horizon − rd.y · slope goes negative towards a pole when |slope| exceeds the horizon's colour:
    the sky is clamped at 0 (radiance = max(horizon − rd.y · slope, 0), through the camera's rays)."""
    scene = _small(camera={"eye": [0.0, 0.0, 0.0], "target": [0.0, pitch, 1.0], "fov_y": 120.0},
                   sky={"kind": "gradient", "horizon": list(horizon), "slope": list(slope)})
    out = tv.render(scene)
    check_output(out, what=str(scene))
    d = out.camera.rays().directions[:, 1:2].float()
    expected = (torch.tensor(horizon) - d * torch.tensor(slope)).clamp_min(0.0)
    assert_close(out.radiance[0].permute(1, 2, 0).reshape(-1, 3), expected, atol=1e-5, what="gradient sky")


@FAST
@given(count=st.integers(2, 3), yaw=st.floats(90.0, 270.0), labels=st.sampled_from([["alpha_volumes"], ["instance"],
       ["alpha_volumes", "instance", "optical_thickness"]]))
def test_jointly_marched_volumes_no_ray_meets_give_zero_labels(count, yaw, labels):
    """Overlapping volumes, marched jointly, that no ray of the image meets (the camera looks away):
    the labels' per-volume alpha shares are zeros of V channels (they were [0, n] and the labels
    raised a shape mismatch)."""
    a = math.radians(yaw)
    volumes = [{"bounds": {"sphere": {"center": [0.0, 0.0, 0.2 * k], "radius": 0.5}}, "density": {"fbm": {"octaves": 1}},
                "sigma_t": 2.0} for k in range(count)]
    scene = _small(camera={"eye": [0.0, 0.0, -3.0], "target": [math.sin(a), 0.0, -3.0 + math.cos(a)], "fov_y": 30.0},
                   lights=[SUN], volumes=volumes)
    out = tv.render(scene, aovs=labels)
    check_output(out, what=str(scene))
    assert (out.alpha == 0).all()
    if "alpha_volumes" in labels:
        assert out.aovs["alpha_volumes"].shape[1] == count and (out.aovs["alpha_volumes"] == 0).all()
    if "instance" in labels:
        assert (out.aovs["instance"] == 0).all()


HUGE = [{"constant": 1e38}, {"grid": {"data": [[[1e30, 0.0], [0.0, 1e38]]]}}, {"fbm": {"octaves": 1, "amplitude": 1e30, "bias": 1e30}},
        {"particles": {"count": 2, "core": 1e30, "amplitude": 1e30}}, {"fur": {"scale": 1e30}}]


@FAST
@given(density=st.sampled_from(HUGE), sigma_t=st.sampled_from([1.0, 1e12]), shading=st.sampled_from(["physical", "shader", "surface"]),
       march=st.sampled_from([{"closed_form": True}, {"closed_form": False}, {"tolerance": 0.1}]),
       light=st.sampled_from([SUN, {"kind": "sun", "direction": [0.3, 1.0, -0.2], "shadow": {"method": "grid", "resolution": 4}},
                              {"kind": "point", "position": [0.0, 0.0, 0.0], "shadow": {"steps": 2}}]))
def test_huge_densities_are_capped(density, sigma_t, shading, march, light):
    """A density far past 1e12 (a constant, grid values, an fbm's amplitude: the schema bounds none
    of them) times sigma_t overflowed float32 to inf, and the march's inf × 0 to NaN: every field's
    density is capped at DENSITY_MAX (1e12), so the medium is opaque and the output finite."""
    scene = _small(camera={"eye": [0.0, 0.2, -3.0], "target": [0.0, 0.0, 0.0]}, lights=[light],
                   sky={"kind": "constant", "radiance": [0.5, 0.5, 0.5]},
                   volumes=[{"bounds": BOUNDS["box"], "density": density, "sigma_t": sigma_t, "shading": shading}])
    scene["march"].update(march if shading == "physical" else {})
    out = tv.render(scene, aovs=["optical_thickness", "alpha_volumes", "instance"])
    check_output(out, what=str(scene))
