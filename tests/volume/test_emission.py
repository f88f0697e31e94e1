"""Emission colour maps, the explosion density and the bloom glow (volume/emission.py,
fields/explosion.py), and the explosion and fire presets.

Ground truth: an emission-only homogeneous sphere with a constant colour map is
L = σe/σt · (1 − e^{−σt·d}) on the chord d (rays and chords rebuilt independently from the exported
camera, as in test_analytic); the glow alone (density 0) is ∫ s·I·c·e^{−k·r³} dt, by quadrature;
the colour map is the seeds' computeColor run on Mesa llvmpipe.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import assert_close
from hypothesis import given, settings
from hypothesis import strategies as st
from test_analytic import camera_rays, sphere_interval

import torchvol as tv
from torchvol.fields import DENSITIES
from torchvol.measure.glsl import gl_context, run_fragment, shadertoy_source
from torchvol.renderer.plan import make_plan
from torchvol.schema.batch import stack
from torchvol.schema.validate import SceneError
from torchvol.volume.emission import explosion_color, explosion_emission

F64 = torch.float64
SEED_MAP = dict(thin=(1.0, 0.9, 0.8), dense=(0.4, 0.15, 0.1), core=(5.6, 7.0, 7.0), edge=(0.72, 0.795, 0.75),
                reach=0.9, overshoot=1.15)


def emissive_sphere(**volume) -> dict:
    return {"image": {"width": 16, "height": 12}, "camera": {"eye": [0.2, 0.3, -3.0], "target": [0.0, 0.0, 0.0], "fov_y": 40.0},
            "volumes": [{"bounds": {"sphere": {"center": [0.0, 0.0, 0.0], "radius": 0.9}}, "density": {"constant": 0.8},
                         "sigma_t": 2.5, "albedo": 0.0, **volume}],
            "march": {"steps": 4, "integrator": "frostbite", "dither": "none"}}


# ---------------------------------------------------------------------------------------------
# The colour map


def test_constant_colour_map_matches_the_emission_absorption_closed_form(one_thread):
    """thin = dense and core = edge = 1 make the map a constant c: σe = scale·c·ρ, σt = sigma_t·ρ,
    L = σe/σt (1 − e^{−σt d}); the frostbite march is exact per segment, so 4 steps suffice."""
    c, scale = (0.9, 0.5, 0.2), 3.0
    flat = {"explosion": {"scale": scale, "thin": c, "dense": c, "core": (1.0, 1.0, 1.0), "edge": (1.0, 1.0, 1.0)}}
    out = tv.render(emissive_sphere(emission_map=flat), dtype=F64)
    eye, dirs, _ = camera_rays(out)
    t0, t1, hit = sphere_interval(eye, dirs, (0.0, 0.0, 0.0), 0.9)
    sigma = 2.5 * 0.8
    expected = (scale * 0.8 / sigma) * -np.expm1(-sigma * (t1 - t0))
    assert hit.sum() > 50
    for k in range(3):
        assert_close(out.radiance[0, k], torch.as_tensor(expected * c[k]), atol=1e-9, what=f"radiance[{k}]")
    assert_close(out.alpha[0, 0], torch.as_tensor(-np.expm1(-sigma * (t1 - t0))), atol=1e-9, what="alpha")
    # the same emission as the constant key, which takes the closed form
    plain = tv.render(emissive_sphere(emission=[scale * x for x in c]), dtype=F64)
    assert "volume0.closed_form" in plain.stats["passes"]
    assert_close(out.radiance, plain.radiance, atol=1e-9, what="map vs emission key")


def test_map_clamps_negative_overshoot_and_density_over_one():
    """The seeds' ramp overshoots past `edge` and goes negative beyond r ≈ 1: emission is 0 there;
    the density mix stops at ρ = 1 (σe still scales with ρ)."""
    params = stack([tv.load_scene({"volumes": [{"emission_map": {"explosion": {"scale": 2.0}}}]})], dtype=F64).volumes[0].emission_map.value
    s = torch.zeros(3, dtype=torch.long)
    points = torch.tensor([[1.2, 0.0, 0.0], [0.0, 0.3, 0.0], [0.0, 0.3, 0.0]], dtype=F64)
    density = torch.tensor([0.5, 1.0, 3.0], dtype=F64)
    e = explosion_emission(params, points, density, s)
    raw = explosion_color(torch.tensor([0.5], dtype=F64), torch.tensor([1.2], dtype=F64),
                          **{k: torch.tensor([v], dtype=F64) for k, v in SEED_MAP.items()})
    assert (raw < 0).all() and (e[0] == 0).all()
    assert_close(e[2], 3.0 * e[1], atol=1e-12, what="density 3 vs 1")
    assert (e[1] > 0).all()


@pytest.mark.gl
@pytest.mark.skipif(gl_context() is None, reason="no OpenGL (moderngl/EGL) context")
def test_colour_map_matches_the_seeds_glsl():
    """The seeds' computeColor on llvmpipe, on a grid of density ∈ [0, 1) × radius ∈ [0, 1.5)."""
    w, h = 64, 32
    body = """
vec3 computeColor(float density, float radius) {
    vec3 result = mix(vec3(1.0, 0.9, 0.8), vec3(0.4, 0.15, 0.1), density);
    vec3 colCenter = 7.0 * vec3(0.8, 1.0, 1.0);
    vec3 colEdge = 1.5 * vec3(0.48, 0.53, 0.5);
    result *= mix(colCenter, colEdge, min(radius / 0.9, 1.15));
    return result;
}
void mainImage(out vec4 o, in vec2 fc) { o = vec4(computeColor(fc.x / 64.0, fc.y / 32.0 * 1.5), 1.0); }
"""
    gl = run_fragment(shadertoy_source(body), w, h)[::-1, :, :3]  # row 0 = fragCoord.y 0.5
    fy, fx = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij")
    density, radius = (fx / 64.0).flatten(), (fy / 32.0 * 1.5).flatten()
    n = density.shape[0]
    ours = explosion_color(density, radius, **{k: torch.tensor(v).expand(n, *np.shape(v)) for k, v in SEED_MAP.items()})
    # measured max error 9.5e-7 (one float32 ulp of values up to 6.1, Mesa llvmpipe)
    assert_close(ours, torch.from_numpy(gl.reshape(-1, 3).copy()), atol=4e-6, what="computeColor")
    assert (ours < 0).any(), "the grid reaches the ramp's negative overshoot"


# ---------------------------------------------------------------------------------------------
# The explosion density


def explosion_field(time: float = 0.0, **params):
    scene = tv.load_scene({"time": time, "volumes": [{"bounds": {"sphere": {"radius": 2.0}}, "density": {"explosion": params}}]})
    batch = stack([scene], dtype=F64)
    vol = batch.volumes[0]
    return DENSITIES["explosion"].fn(vol.density.value, batch.time)


def test_explosion_is_a_displaced_ball_animated_and_seeded():
    g = torch.Generator().manual_seed(0)
    p = torch.rand(4000, 3, generator=g, dtype=F64) * 4.0 - 2.0
    s = torch.zeros(4000, dtype=torch.long)
    d = explosion_field(seed=1)(p, s)
    r = p.norm(dim=1)
    assert d.min() >= 0 and d.max() <= 1
    assert (d[r > 1.0 + 0.6 * 0.5] == 0).all(), "nothing beyond the largest displacement"
    assert (d[r < 0.2] == 1).all(), "a full core"
    assert torch.equal(explosion_field(seed=1)(p, s), d)
    assert not torch.equal(explosion_field(seed=2)(p, s), d)
    assert not torch.equal(explosion_field(time=1.0, seed=1)(p, s), d), "time drifts the noise"
    grown = explosion_field(time=2.0, seed=1, growth=0.5, drift=(0.0, 0.0, 0.0))
    assert_close(grown(p * 2.0, s), d, atol=1e-12, what="R(t) = radius·(1 + growth·t) scales the whole ball")


@settings(max_examples=40, deadline=None)
@given(scale=st.floats(1e-6, 1e6), radius=st.floats(1e-3, 1e3), sharp=st.floats(1e-3, 1e3),
       x=st.floats(-1e6, 1e6), t=st.floats(-1e4, 1e4))
def test_explosion_and_map_stay_finite(scale, radius, sharp, x, t):
    p = torch.tensor([[x, 0.0, 0.0], [0.0, 0.0, 0.0], [x * 1e-6, x, -x]], dtype=torch.float32)
    s = torch.zeros(3, dtype=torch.long)
    field = explosion_field(time=t, radius=radius, sharpness=sharp, growth=1.0)
    d = field(p.double(), s)
    assert torch.isfinite(d).all() and d.min() >= 0 and d.max() <= 1
    params = stack([tv.load_scene({"volumes": [{"emission_map": {"explosion": {"scale": scale, "radius": radius}}}]})]).volumes[0].emission_map.value
    e = explosion_emission(params, p, d.float(), s)
    assert torch.isfinite(e).all() and e.min() >= 0


# ---------------------------------------------------------------------------------------------
# The glow


def test_bloom_alone_is_the_glow_integral(one_thread):
    """Density 0: the ray through the light (the centre pixel of an odd image) sees
    ∫ strength·I·c·e^{−k r³} dt over the chord."""
    strength, k, intensity, color = 0.5, 1.3, 2.0, (1.0, 0.5, 0.25)
    scene = {"image": {"width": 9, "height": 9}, "camera": {"eye": [0.0, 0.0, -3.0], "target": [0.0, 0.0, 0.0], "fov_y": 30.0},
             "lights": [{"kind": "point", "position": [0.0, 0.0, 0.0], "color": color, "intensity": intensity}],
             "volumes": [{"bounds": {"sphere": {"radius": 1.5}}, "density": {"fbm": {"bias": -5.0}}, "albedo": 0.0,
                          "bloom": {"light": 0, "strength": strength, "falloff": k}}],
             "march": {"steps": 512, "integrator": "frostbite", "dither": "none"}}
    out = tv.render(scene, dtype=F64)
    x = np.linspace(-1.5, 1.5, 200001)
    glow = np.trapezoid(strength * intensity * np.exp(-k * np.abs(x) ** 3), x)
    assert_close(out.radiance[0, :, 4, 4], torch.tensor(color, dtype=F64) * glow, atol=1e-4 * glow, what="glow")
    assert out.stats["passes"] == ["rays", "volume0.march", "volume0.bloom", "composite"]
    assert out.alpha.max() == 0


def test_bloom_needs_a_point_light():
    scene = emissive_sphere(bloom={"light": 0})
    with pytest.raises(SceneError, match=r"volumes\[0\]\.bloom\.light"):
        tv.load_scene(scene)
    scene["lights"] = [{"kind": "sun"}]
    with pytest.raises(SceneError, match=r"volumes\[0\]\.bloom\.light"):
        tv.load_scene(scene)
    scene["lights"] = [{"kind": "point"}]
    scene["march"] = {"tolerance": 1e-3}
    with pytest.raises(SceneError, match=r"march\.tolerance"):
        tv.load_scene(scene)
    with pytest.raises(SceneError, match="physical"):
        tv.load_scene(emissive_sphere(emission_map={"explosion": {}}, shading="shader"))


# ---------------------------------------------------------------------------------------------
# The plan and the presets


def test_a_volume_without_the_keys_plans_no_extra_work():
    plan = make_plan(tv.load_scene(emissive_sphere()))
    vol = plan.volumes[0]
    assert vol.strategy == "closed_form" and vol.emission_map is None and vol.bloom is None
    assert not any("emission" in n or "bloom" in n for n in plan.names())
    mapped = make_plan(tv.load_scene(emissive_sphere(emission_map={"explosion": {}}))).volumes[0]
    assert mapped.strategy == "march" and mapped.names() == ["volume0.march", "volume0.emission_map"]


def test_the_error_controlled_march_integrates_the_colour_map(one_thread):
    scene = tv.load_scene(tv.preset("explosion", width=8, height=6), {"volumes[0].bloom": None, "march.steps": 256})
    fixed = tv.render(scene, dtype=F64)
    adaptive = tv.render(tv.load_scene(scene, {"march.tolerance": 1e-3}), dtype=F64)
    assert "volume0.emission_map" in adaptive.stats["passes"]
    assert_close(adaptive.radiance, fixed.radiance, atol=3e-3 * float(fixed.radiance.max()), what="tolerance vs 256 steps")


def test_camera_inside_the_explosion_renders_finite(one_thread):
    scene = tv.load_scene(tv.preset("explosion", width=12, height=10), {"camera.eye": [0.0, 0.1, -0.2], "march.steps": 12})
    out = tv.render(scene)
    assert torch.isfinite(out.radiance).all() and out.radiance.min() >= 0
    assert out.radiance.mean() > 0.5, "inside the hot core"


@pytest.mark.parametrize("name", ["explosion", "fire"])
def test_presets_at_odd_sizes(name, one_thread):
    scene = tv.load_scene(tv.preset(name, width=17, height=9, time=1.5, seed=3), {"march.steps": 12})
    out = tv.render(scene)
    for key, value in [("image", out.image), ("radiance", out.radiance), ("depth", out.depth), ("alpha", out.alpha)]:
        assert torch.isfinite(value).all(), key
    assert out.image.shape == (1, 3, 9, 17) and 0 <= out.image.min() and out.image.max() <= 1
    assert out.radiance.max() > 1.0, "HDR radiance reaches the tonemap"
    passes = out.stats["passes"]
    assert set(passes) <= set(out.stats["plan"]["passes"])
    assert not any("shadow" in p for p in passes)
    assert ("sky" in passes) == (name == "fire")
    assert {"volume0.emission_map", "volume0.bloom", "post.tonemap.aces"} <= set(passes)
    if name == "fire":
        assert "media.march" in passes and "volume1.emission_map" not in passes  # the flames and the smoke together


def test_preset_parameters_are_checked():
    with pytest.raises(ValueError, match="seed"):
        tv.preset("fire", seed=-1)
    with pytest.raises(ValueError, match="time"):
        tv.preset("explosion", time=float("nan"))


def test_fire_recipe_draws_renderable_scenes(one_thread):
    recipe = tv.Recipe.load(Path(__file__).resolve().parents[2] / "datasets" / "fire.toml",
                            {"image.width": 10, "image.height": 8, "march.steps": 8})
    scenes = [recipe.sample(i, seed=1) for i in range(3)]
    assert len({s.volumes[0].density.explosion.seed for s in scenes}) == 3
    out = tv.render(scenes, seed=[0, 1, 2])
    assert torch.isfinite(out.radiance).all() and out.radiance.amax() > 1.0
