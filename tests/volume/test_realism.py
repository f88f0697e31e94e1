"""The realism terms of physical shading (docs/VOLUMES.md): sky light in-scattered
(`volumes[i].ambient`), Wrenninge's multiple-scattering octaves (`multiple_scattering`) and the
density faded towards the bounds (`edge`). Without them physical shading is single scattering,
to the bit; with them each term matches its closed form in a homogeneous medium."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import assert_close
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import torchvol as tv
from torchvol.renderer.plan import make_plan
from torchvol.volume.ambient import fibonacci_sphere

SUN = {"kind": "sun", "direction": [0.3, 0.8, -0.5], "color": [1.0, 0.9, 0.8], "intensity": 2.0}
POINT = {"kind": "point", "position": [0.4, 1.2, -0.9], "color": [1.0, 1.0, 1.0], "intensity": 3.0, "shadow": {"steps": 4}}


def puff(**volume) -> dict:
    """A small fbm puff in a sphere, a shadowed sun and a point light, a constant sky."""
    return {
        "image": {"width": 12, "height": 10},
        "camera": {"eye": [0.2, 0.4, -3.0], "target": [0, 0, 0], "fov_y": 40.0},
        "sky": {"kind": "constant", "radiance": [0.3, 0.4, 0.6]},
        "lights": [{**SUN, "shadow": {"steps": 4}}, POINT],
        "volumes": [{"bounds": {"sphere": {"radius": 1.0}},
                     "density": {"fbm": {"octaves": 3, "frequency": 2.0, "bias": 0.6, "amplitude": 1.5, "radial": 1.0}},
                     "sigma_t": 6.0, "albedo": 0.9, "phase": {"hg": {"g": 0.6}}, **volume}],
        "march": {"steps": 16},
    }


def homogeneous(*, sigma_t: float, albedo: float, lights=(), **volume) -> dict:
    """A constant density 1 in the box [-1, 1]³, seen along +z from z = −4 at 9×9 (the centre
    pixel's ray is the z axis), no sky, frostbite steps (exact for a constant source)."""
    return {
        "image": {"width": 9, "height": 9},
        "camera": {"eye": [0.0, 0.0, -4.0], "target": [0, 0, 0], "fov_y": 20.0},
        "lights": list(lights),
        "volumes": [{"bounds": {"box": {"min": [-1, -1, -1], "max": [1, 1, 1]}}, "density": {"constant": 1.0},
                     "sigma_t": sigma_t, "albedo": albedo, **volume}],
        "march": {"steps": 8, "integrator": "frostbite", "dither": "none"},
    }


def centre(out) -> torch.Tensor:
    return out.radiance[0, :, 4, 4].double()


# ---------------------------------------------------------------------------------------------
# Absent: single scattering, to the bit, and nothing in the plan


def test_absent_terms_are_not_in_the_plan():
    out = tv.render(puff())
    assert not any("ambient" in p for p in out.stats["passes"] + out.stats["plan"]["passes"])
    vp = make_plan(tv.load_scene(puff())).volumes[0]
    assert (vp.ambient, vp.ambient_pass, vp.multiple) == (False, None, False)


def test_one_octave_is_single_scattering_to_the_bit(one_thread):
    """The octave path with one octave runs octave 0, which is single scattering itself (sun and
    point light, both shadowed)."""
    single = tv.render(puff())
    one = tv.render(puff(multiple_scattering={"octaves": 1, "a": 0.3, "b": 0.4, "c": 0.2}))
    assert torch.equal(single.radiance, one.radiance) and torch.equal(single.depth, one.depth)


def test_black_unoccluded_ambient_adds_nothing_to_the_bit(one_thread):
    single = tv.render(puff())
    ambient = tv.render(puff(ambient={"radiance": [0.0, 0.0, 0.0], "visibility": "none"}))
    assert torch.equal(single.radiance, ambient.radiance)
    assert ambient.stats["passes"] == single.stats["passes"]  # V = 1 marches nothing


def test_terms_are_planned_and_run():
    scene = puff(ambient={}, multiple_scattering={}, edge={"width": 0.3})
    out = tv.render(scene)
    assert "volume0.ambient" in out.stats["passes"] and out.stats["passes"] == out.stats["plan"]["passes"]
    single = tv.render(puff())
    assert out.radiance.mean() > single.radiance.mean()  # sky light and higher orders only add light
    assert torch.isfinite(out.radiance).all()


# ---------------------------------------------------------------------------------------------
# Ambient: closed forms in a homogeneous medium


@pytest.mark.parametrize("sigma_t, albedo", [(0.7, 0.9), (3.0, 0.5), (12.0, 1.0)])
def test_unoccluded_ambient_matches_the_closed_form(sigma_t, albedo, one_thread):
    """V = 1, constant L: L = ∫₀^d e^{−σt t} σs L dt = S/σt (1 − e^{−σt d}), S = σs·L, d = 2."""
    L = torch.tensor([0.2, 0.5, 1.3], dtype=torch.float64)
    out = tv.render(homogeneous(sigma_t=sigma_t, albedo=albedo, ambient={"radiance": L.tolist(), "visibility": "none"}))
    expected = albedo * sigma_t * L / sigma_t * (1.0 - math.exp(-sigma_t * 2.0))
    assert_close(centre(out), expected, atol=1e-5, what="ambient radiance")
    assert out.stats["passes"] == ["rays", "volume0.march", "composite"]


@pytest.mark.parametrize("y, scale", [(0.0, 1.0), (0.5, 1.0), (-0.6, 0.4)])
def test_ambient_visibility_is_the_transmittance_to_the_top(y, scale, one_thread):
    """A horizontal ray at height y: V = e^{−scale·σt (1 − y)} (straight up to the box top, exact
    for a homogeneous medium), constant along the ray, so L = αL_amb V (1 − e^{−σt d})."""
    sigma_t, albedo, L = 1.5, 0.8, 0.7
    scene = homogeneous(sigma_t=sigma_t, albedo=albedo, ambient={"radiance": [L] * 3, "sigma_scale": scale, "steps": 3})
    scene["camera"].update(eye=[0.0, y, -4.0], target=[0.0, y, 0.0])
    out = tv.render(scene)
    v = math.exp(-scale * sigma_t * (1.0 - y))
    assert_close(centre(out), albedo * L * v * (1.0 - math.exp(-2 * sigma_t)), atol=1e-5, what="ambient with visibility")
    assert "volume0.ambient" in out.stats["passes"]


def test_ambient_gradient_and_sky_mean(one_thread):
    """`top` grades the radiance linearly over the bounds' height (a horizontal ray at height y sees
    lerp(radiance, top, (y + 1)/2)); without `radiance` it is the sky's mean over the sphere (a
    constant sky's radiance)."""
    bottom, top, y = [0.1, 0.2, 0.3], [0.9, 0.8, 0.7], 0.5
    scene = homogeneous(sigma_t=2.0, albedo=1.0, ambient={"radiance": bottom, "top": top, "visibility": "none"})
    scene["camera"].update(eye=[0.0, y, -4.0], target=[0.0, y, 0.0])
    h = (y + 1) / 2
    expected = torch.lerp(torch.tensor(bottom, dtype=torch.float64), torch.tensor(top, dtype=torch.float64), h)
    assert_close(centre(tv.render(scene)), expected * (1 - math.exp(-4.0)), atol=1e-5, what="graded ambient")
    sky = homogeneous(sigma_t=2.0, albedo=1.0, ambient={"visibility": "none"})
    sky["sky"] = {"kind": "constant", "radiance": [0.25, 0.5, 0.75]}
    # the sky is also seen through the medium: T·L_sky + (1 − T)·L_sky = L_sky
    assert_close(centre(tv.render(sky)), torch.tensor([0.25, 0.5, 0.75], dtype=torch.float64), atol=1e-5,
                 what="sky-mean ambient of a constant sky")


def test_fibonacci_directions_are_unit_and_balanced():
    d = fibonacci_sphere(64, dtype=torch.float64, device="cpu")
    assert_close(d.norm(dim=1), torch.ones(64, dtype=torch.float64), what="norm")
    assert d.mean(dim=0).abs().max() < 0.02


# ---------------------------------------------------------------------------------------------
# Multiple scattering: the octave sum in closed form, and its energy bound


def octave_closed_form(sigma_t, albedo, octaves, a, c, g, cos, d=2.0):
    """Unshadowed sun of irradiance E = 2·color, HG g: Σᵢ aⁱ σs E p(θ; g cⁱ) (1 − e^{−σt d})/σt."""
    def hg(gi):
        return (1 - gi * gi) / (4 * math.pi * (1 + gi * gi - 2 * gi * cos) ** 1.5)

    e = 2.0 * torch.tensor(SUN["color"], dtype=torch.float64)
    return albedo * e * sum(a**i * hg(g * c**i) for i in range(octaves)) * (1 - math.exp(-sigma_t * d))


def test_unshadowed_octaves_match_the_closed_form(one_thread):
    sigma_t, albedo, g, octaves, a, c = 2.5, 0.9, 0.7, 5, 0.6, 0.4
    scene = homogeneous(sigma_t=sigma_t, albedo=albedo, lights=[SUN], phase={"hg": {"g": g}},
                        multiple_scattering={"octaves": octaves, "a": a, "b": 0.8, "c": c})
    out = tv.render(scene)
    assert out.stats["passes"] == ["rays", "volume0.closed_form", "composite"]  # a constant source: still exact
    sun = torch.tensor(SUN["direction"], dtype=torch.float64)
    cos = float(sun[2] / sun.norm())  # the centre ray looks along +z
    assert_close(centre(out), octave_closed_form(sigma_t, albedo, octaves, a, c, g, cos), atol=1e-5, what="octave sum")


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(octaves=st.integers(1, 8), a=st.floats(0.01, 0.95), b_extra=st.floats(0.0, 1.0), c=st.floats(0.0, 1.0),
       albedo=st.floats(0.0, 1.0), sigma_t=st.floats(0.01, 50.0))
def test_octaves_never_exceed_the_albedo_bound(octaves, a, b_extra, c, albedo, sigma_t, one_thread):
    """Isotropic phase, shadowed sun: each octave is at most its unshadowed value aⁱ·α·E/4π·(1 −
    e^{−τ}), so the sum is at most α·E/4π·(1 − aᴷ)/(1 − a) ≤ α·E/(4π(1 − a)); and adding octaves
    never removes light."""
    b = a + (1.0 - a) * b_extra  # a ≤ b ≤ 1
    lights = [{**SUN, "shadow": {"steps": 6}}]
    scene = homogeneous(sigma_t=sigma_t, albedo=albedo, lights=lights,
                        multiple_scattering={"octaves": octaves, "a": a, "b": b, "c": c})
    got = tv.render(scene).radiance[0].double()
    e = 2.0 * torch.tensor(SUN["color"], dtype=torch.float64)
    bound = albedo * e / (4 * math.pi) * (1 - a**octaves) / (1 - a) * (1 - math.exp(-2 * sigma_t))  # the centre's chord
    assert torch.isfinite(got).all()
    assert (got[:, 4, 4] <= bound * (1 + 1e-5) + 1e-7).all(), f"ratio {(got[:, 4, 4] / bound.clamp_min(1e-30)).tolist()}"
    assert (got <= (albedo * e / (4 * math.pi * (1 - a)))[:, None, None] + 1e-6).all()
    fewer = tv.render(tv.load_scene(scene, {"volumes[0].multiple_scattering.octaves": max(octaves - 1, 1)}))
    assert (fewer.radiance[0].double() <= got + 1e-7).all()


# ---------------------------------------------------------------------------------------------
# Edge falloff


@pytest.mark.parametrize("bounds", [{"sphere": {"radius": 1.0}}, {"box": {"min": [-1, -0.8, -1], "max": [1, 0.8, 1]}},
                                    {"slab": {"y_min": -1.0, "y_max": 1.0}}])
def test_edge_fades_to_zero_at_the_bounds(bounds):
    """Through the bounds' surface the density is 0; a width inside, the field's own."""
    from torchvol.renderer.executor import RenderContext
    from torchvol.schema.batch import stack

    scene = tv.load_scene({"volumes": [{"bounds": bounds, "density": {"constant": 2.0}, "edge": {"width": 0.25}}]})
    batch = stack([scene])
    ctx = RenderContext(batch, make_plan(scene), seeds=[0], device="cpu")
    field = ctx.volumes[0].field
    top = 0.8 if "box" in bounds else 1.0
    p = torch.tensor([[0.0, top, 0.0], [0.0, top - 0.125, 0.0], [0.0, top - 0.25, 0.0], [0.0, 0.0, 0.0], [0, top + 1, 0]])
    s = torch.zeros(5, dtype=torch.long)
    assert_close(field(p, s), torch.tensor([0.0, 1.0, 2.0, 2.0, 0.0]), atol=1e-5, what="faded density")
    assert make_plan(scene).volumes[0].strategy == "march"  # no longer homogeneous: no closed form


def test_edge_base_is_a_flat_floor():
    from torchvol.renderer.executor import RenderContext
    from torchvol.schema.batch import stack

    scene = tv.load_scene({"volumes": [{"bounds": {"sphere": {"radius": 1.0}}, "density": {"constant": 1.0},
                                        "edge": {"width": 0.2, "base": -0.3}}]})
    ctx = RenderContext(stack([scene]), make_plan(scene), seeds=[0], device="cpu")
    p = torch.tensor([[0.5, -0.35, 0.0], [0.5, -0.3, 0.0], [0.5, -0.2, 0.0], [0.5, -0.1, 0.0], [0.0, 0.5, 0.0]])
    got = ctx.volumes[0].field(p, torch.zeros(5, dtype=torch.long))
    assert_close(got, torch.tensor([0.0, 0.0, 0.5, 1.0, 1.0]), atol=1e-5, what="density over the base")


def test_edge_leaves_no_silhouette(one_thread):
    """A constant sphere shows a hard disc; with the edge, alpha rises smoothly from 0 at the rim."""
    scene = {"image": {"width": 32, "height": 32}, "camera": {"eye": [0, 0, -3.0], "target": [0, 0, 0], "fov_y": 45.0},
             "volumes": [{"bounds": {"sphere": {"radius": 1.0}}, "density": {"constant": 1.0}, "sigma_t": 8.0,
                          "edge": {"width": 0.5}}], "march": {"steps": 64}}
    hard = tv.render(tv.load_scene(scene, {"volumes[0].edge": None})).alpha[0, 0]
    soft = tv.render(scene).alpha[0, 0]
    assert float((hard[:, 1:] - hard[:, :-1]).abs().max()) > 0.9  # the disc's rim: a jump of ~1 between pixels
    assert float((soft[:, 1:] - soft[:, :-1]).abs().max()) < 0.45


# ---------------------------------------------------------------------------------------------
# Refusals and hard cases


@pytest.mark.parametrize("overrides, key", [
    ({"volumes[0].ambient": {}, "sky": None}, "volumes[0].ambient.radiance"),
    ({"volumes[0].multiple_scattering": {"a": 0.8, "b": 0.5}}, "volumes[0].multiple_scattering"),
    ({"volumes[0].ambient": {"direction": [0, 0, 0]}}, "volumes[0].ambient.direction"),
    ({"volumes[0].ambient": {"radiance": [1, -1, 0]}}, "volumes[0].ambient.radiance"),
    ({"volumes[0].ambient": {}, "volumes[0].shading": "shader"}, "volumes[0].ambient"),
    ({"volumes[0].edge": {"width": 0.0}}, "volumes[0].edge.width"),
])
def test_bad_values_are_refused_naming_the_key(overrides, key):
    with pytest.raises(ValueError, match=key.replace("[", r"\[").replace("]", r"\]")):
        tv.load_scene(puff(), overrides)


@pytest.mark.parametrize("overrides", [
    {"volumes[0].sigma_t": 1e6, "volumes[0].albedo": 1.0},
    {"volumes[0].sigma_t": 0.0},
    {"camera.eye": [0.0, 0.1, 0.2]},  # inside the medium
    {"lights[0].direction": [0.0, 0.0, -1.0], "volumes[0].phase": {"hg": {"g": 0.99}}},  # looking into the sun
    {"volumes[0].multiple_scattering.b": 1e-6, "volumes[0].multiple_scattering.a": 0.0,
     "volumes[0].multiple_scattering.octaves": 16},
    {"volumes[0].edge.width": 1e-6, "volumes[0].ambient.sigma_scale": 0.0},
    {"volumes[0].edge.width": 100.0, "sky": {"kind": "gradient", "horizon": [0.5, 0.6, 0.7], "slope": [0.1, 0.1, 0.1]}},
    {"march.tolerance": 0.01},
    {"sky": {"kind": "atmosphere"}, "lights[0].direction": [0.0, 0.02, 1.0]},  # sky mean of an atmosphere at sunset
    {"lights[0].shadow.method": "grid", "lights[0].shadow.resolution": 8, "volumes[0].bounds": {"box": {}}},
])
def test_hard_cases_stay_finite(overrides, one_thread):
    base = puff(ambient={"top": [1.0, 1.0, 1.0]}, multiple_scattering={"octaves": 3}, edge={"width": 0.2})
    out = tv.render(tv.load_scene(base, overrides))
    for name, t in (("radiance", out.radiance), ("depth", out.depth), ("alpha", out.alpha)):
        assert torch.isfinite(t).all(), name
    assert (out.radiance >= 0).all()


def test_cloud_puff_parameters():
    """cloud-puff turns the terms on; `realism=False` is plain single scattering; `sun` picks a look."""
    on, off = tv.preset("cloud-puff", width=8, height=8), tv.preset("cloud-puff", width=8, height=8, realism=False)
    assert all(getattr(on.volumes[0], k) is not None for k in ("ambient", "multiple_scattering", "edge"))
    assert all(getattr(off.volumes[0], k) is None for k in ("ambient", "multiple_scattering", "edge"))
    assert "volume0.ambient" in make_plan(on).names() and "volume0.ambient" not in make_plan(off).names()
    sunset = tv.preset("cloud-puff", width=8, height=8, sun="sunset")
    assert sunset.lights[0].color[2] < 0.5 and sunset.lights[0].direction[1] < 0.2
    with pytest.raises(ValueError, match="cloud-puff.sun"):
        tv.preset("cloud-puff", sun="noon")
