"""Shadows across media and surfaces: a shadow ray sees every volume it crosses and the terrain.

Analytic oracles: a homogeneous slab above a flat terrain darkens it by exp(−σ·thickness/cos θ),
for a sun and for a point light behind it;
the in-scatter of one homogeneous volume under (or over) another is the single-scattering
integral with the product of both transmittances; a scene with one volume and no surface plans no
occluders (its shadows are the volume's own march, as before)."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import assert_close

import torchvol as tv
from torchvol.renderer.plan import make_plan


def _sun(direction, intensity=2.0, steps=4):
    return {"kind": "sun", "direction": list(direction), "color": [1.0, 1.0, 1.0], "intensity": intensity,
            "shadow": {"steps": steps}}


@pytest.mark.parametrize("theta", [0.0, 35.0, 60.0])
def test_slab_shadow_on_a_plane_is_beer_lambert(theta, one_thread):
    sigma, thickness, color, intensity = 1.3, 0.7, 0.6, 2.0
    c, s_ = math.cos(math.radians(theta)), math.sin(math.radians(theta))
    scene = {
        "image": {"width": 9, "height": 7},
        "camera": {"eye": [0.0, 0.9, -1.0], "target": [0.0, 0.0, 0.0], "fov_y": 40.0},  # below the slab, every ray on the plane
        "lights": [_sun((s_, c, 0.3 * s_), intensity)],
        "terrain": {"amplitude": 0.0, "base": 0.0, "color": [color] * 3, "ambient": [0.0] * 3},
        "volumes": [{"bounds": {"slab": {"y_min": 1.0, "y_max": 1.0 + thickness}}, "density": {"constant": 1.0},
                     "sigma_t": sigma, "albedo": 0.5}],
    }
    out = tv.render(scene, dtype=torch.float64)
    cos_theta = c / math.sqrt(1.0 + (0.3 * s_) ** 2)  # the sun's angle from the plane's normal
    expected = color * intensity * cos_theta * math.exp(-sigma * thickness / cos_theta)
    assert_close(out.radiance, expected, atol=1e-9, what="radiance of the plane under the slab")
    assert "terrain.shadow0.volume0" in out.stats["passes"]


def test_a_point_light_behind_a_slab(one_thread):
    """A point light above a homogeneous slab over a flat plane: each plane point receives
    I·cos θ/r² · exp(−σ·thickness/cos θ), θ and r towards the light (the shadow ray ends there)."""
    sigma, thickness, color, intensity, light = 0.9, 0.6, 0.7, 5.0, (0.2, 2.5, 0.1)
    scene = {
        "image": {"width": 9, "height": 7},
        "camera": {"eye": [0.0, 0.9, -1.0], "target": [0.0, 0.0, 0.0], "fov_y": 40.0},
        "lights": [{"kind": "point", "position": list(light), "color": [1.0, 1.0, 1.0], "intensity": intensity,
                    "shadow": {"steps": 4}}],
        "terrain": {"amplitude": 0.0, "base": 0.0, "color": [color] * 3, "ambient": [0.0] * 3},
        "volumes": [{"bounds": {"slab": {"y_min": 1.0, "y_max": 1.0 + thickness}}, "density": {"constant": 1.0},
                     "sigma_t": sigma, "albedo": 0.5}],
    }
    out = tv.render(scene, dtype=torch.float64)
    cam = out.camera
    h, w = out.depth.shape[-2:]
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    pixels = torch.stack([u, v, torch.ones_like(u)], dim=-1).reshape(-1, 3)
    in_camera = (torch.linalg.inv(cam.K[0].double()) @ pixels.T).T * out.depth[0, 0].double().reshape(-1, 1)
    to_world = torch.linalg.inv(cam.world_to_camera[0].double())
    points = (to_world[:3, :3] @ in_camera.T).T + to_world[:3, 3]
    assert float(points[:, 1].abs().max()) < 1e-6  # every pixel sees the plane, its depth on it
    toward = torch.tensor(light, dtype=torch.float64) - points
    r = toward.norm(dim=1)
    cos = toward[:, 1] / r
    expected = color * intensity * cos / r**2 * torch.exp(-sigma * thickness / cos)
    # outputs (radiance, and the depth the points come from) are float32
    assert_close(out.radiance[0, 0].reshape(-1).double(), expected, atol=1e-6, what="radiance of the plane under the point light")


def test_terrain_shadow_sees_every_volume(one_thread):
    """Two stacked slabs: the plane's shadow is the product of both (exp of the summed optical depths)."""
    scene = {
        "image": {"width": 5, "height": 5},
        "camera": {"eye": [0.0, 0.9, -1.0], "target": [0.0, 0.0, 0.0], "fov_y": 40.0},
        "lights": [_sun((0.0, 1.0, 0.0))],
        "terrain": {"amplitude": 0.0, "color": [1.0, 1.0, 1.0], "ambient": [0.0] * 3},
        "volumes": [{"bounds": {"slab": {"y_min": 1.0, "y_max": 1.5}}, "density": {"constant": 1.0}, "sigma_t": 0.8},
                    {"bounds": {"slab": {"y_min": 2.0, "y_max": 2.25}}, "density": {"constant": 2.0}, "sigma_t": 1.5}],
    }
    out = tv.render(scene, dtype=torch.float64)
    assert_close(out.radiance, 2.0 * math.exp(-0.8 * 0.5 - 3.0 * 0.25), atol=1e-9, what="plane under two slabs")


@pytest.mark.parametrize("lit_from", ["above", "below"])
def test_two_volumes_shadow_each_other(lit_from, one_thread):
    """A horizontal ray through a homogeneous box (σ1, albedo a, isotropic) lit straight along y by a
    sun whose light first crosses a second homogeneous slab (σ2, thickness h2): the single-scattering
    radiance is a·σ1/(4π)·E·exp(−σ1·h_own)·exp(−σ2·h2)·(1 − exp(−σ1 L))/σ1, the product of both
    transmittances towards the sun."""
    s1, s2, a, e, y0, top, bottom, width, h2 = 0.9, 1.7, 0.8, 3.0, 0.1, 0.4, -0.4, 1.2, 0.3
    up = lit_from == "above"
    other = {"y_min": 1.0, "y_max": 1.0 + h2} if up else {"y_min": -1.0 - h2, "y_max": -1.0}
    scene = {
        "image": {"width": 5, "height": 5},
        "camera": {"eye": [-3.0, y0, 0.0], "target": [0.0, y0, 0.0], "fov_y": 10.0},  # the centre pixel: horizontal
        "lights": [_sun((0.0, 1.0 if up else -1.0, 0.0), e)],
        "volumes": [{"bounds": {"box": {"min": [-width / 2, bottom, -0.5], "max": [width / 2, top, 0.5]}},
                     "density": {"constant": 1.0}, "sigma_t": s1, "albedo": a},
                    {"bounds": {"slab": other}, "density": {"constant": 1.0}, "sigma_t": s2, "albedo": 0.0}],
        "march": {"steps": 8, "dither": "none", "min_transmittance": 0.0},
    }
    out = tv.render(scene, dtype=torch.float64)
    own = (top - y0) if up else (y0 - bottom)
    expected = a * s1 / (4 * math.pi) * e * math.exp(-s1 * own) * math.exp(-s2 * h2) * (1 - math.exp(-s1 * width)) / s1
    assert_close(out.radiance[0, :, 2, 2], expected, atol=1e-9, what="in-scatter under the other volume")
    assert "volume0.shadow0.volume1" in out.stats["passes"]


def test_one_volume_without_surface_plans_no_occluders():
    scene = tv.preset("cloud-puff", width=8, height=8)
    plan = make_plan(scene)
    assert all(li.occluders == () and not li.terrain for v in plan.volumes for li in v.lights)
    assert plan.terrain is None and not any(".volume" in n or "terrain" in n for n in plan.names())


def test_unshadowed_lights_see_no_occluders():
    """Shadows are simulated only for lights with `shadow`: no cross pass, no terrain shadow pass."""
    scene = {"image": {"width": 6, "height": 5}, "lights": [{"kind": "sun", "direction": [0.2, 1.0, 0.1]}],
             "terrain": {"amplitude": 0.3},
             "volumes": [{"bounds": {"slab": {"y_min": 1.0, "y_max": 1.5}}},
                         {"bounds": {"slab": {"y_min": 2.0, "y_max": 2.5}}}]}
    names = make_plan(tv.load_scene(scene)).names()
    assert not any("shadow" in n for n in names), names


def test_grid_shadows_see_the_other_volumes_grid(one_thread):
    """`shadow.method = "grid"`: the plane under two homogeneous boxes, each looked up in its own sun
    grid where the shadow ray enters it, against the analytic product. The grid integrates each
    box's chord on its planes (Simpson on nodes inside the chord), so a thin layer's hard faces
    cost it accuracy: measured 4.1e-2 relative at resolution 128 (the march: exact)."""
    theta = math.radians(30.0)
    sun = {**_sun((math.sin(theta), math.cos(theta), 0.0)), "shadow": {"method": "grid", "resolution": 128}}
    box = lambda y0, y1: {"box": {"min": [-3.0, y0, -3.0], "max": [3.0, y1, 3.0]}}  # noqa: E731
    scene = {
        "image": {"width": 5, "height": 5},
        "camera": {"eye": [0.0, 0.9, -1.0], "target": [0.0, 0.0, 0.0], "fov_y": 30.0},
        "lights": [sun],
        "terrain": {"amplitude": 0.0, "color": [1.0, 1.0, 1.0], "ambient": [0.0] * 3},
        "volumes": [{"bounds": box(1.0, 1.5), "density": {"constant": 1.0}, "sigma_t": 0.8},
                    {"bounds": box(2.0, 2.25), "density": {"constant": 2.0}, "sigma_t": 1.5}],
    }
    out = tv.render(scene, dtype=torch.float64)
    expected = 2.0 * math.cos(theta) * math.exp(-(0.8 * 0.5 + 3.0 * 0.25) / math.cos(theta))
    assert_close(out.radiance / expected, 1.0, atol=6e-2, what="plane under two boxes, grid shadows (relative)")
    assert {"terrain.shadow0.volume0", "terrain.shadow0.volume1"} <= set(out.stats["passes"])


def test_multi_layer_cumulus_shadows_the_fog(one_thread):
    """`multi-layer` seen from between its layers, looking down (no camera ray reaches the cumulus):
    the fog with the cumulus above is never brighter than without it, and the cumulus prints both
    dark patches and lit gaps onto it."""
    overrides = {"image.width": 16, "image.height": 12, "camera.eye": [0.0, 2.5, -3.0], "camera.target": [0.0, 0.0, 2.0],
                 "camera.fov_y": 30.0}
    scene = tv.load_scene("multi-layer", overrides).model_dump()
    fog = scene["volumes"][1]  # a low ground fog, under the camera (the preset's rises into the cloud bases)
    fog["bounds"]["box"]["max"] = (30.0, 1.6, 48.0)
    fog["density"]["exponential"]["scale_height"], fog["sigma_t"] = 0.4, 3.0
    with_cumulus = tv.render(scene)
    fog_only = tv.render({**scene, "volumes": scene["volumes"][1:]})
    assert "volume1.shadow0.volume0" in with_cumulus.stats["passes"]
    ratio = with_cumulus.radiance[0, 1] / fog_only.radiance[0, 1]
    assert bool(torch.isfinite(ratio).all()) and float(ratio.max()) <= 1.0 + 1e-5
    assert float(ratio.min()) < 0.7 and float(ratio.max()) > 0.95, (float(ratio.min()), float(ratio.max()))


@pytest.mark.parametrize("direction", [(1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.3, 1e-7, -0.2)])
def test_grazing_and_upward_shadow_rays_stay_finite(direction, one_thread):
    """A sun on the horizon (shadow rays along the slabs' planes, to their reach) or below the ground."""
    scene = {"image": {"width": 7, "height": 5}, "camera": {"eye": [0.0, 1.0, -3.0], "target": [0.0, 0.0, 0.0]},
             "lights": [_sun(direction, steps=3)], "terrain": {"amplitude": 0.4, "steps": 32},
             "volumes": [{"bounds": {"slab": {"y_min": 0.5, "y_max": 1.5}}, "sigma_t": 0.3},
                         {"bounds": {"sphere": {"center": [0.0, 0.8, 0.0], "radius": 0.4}}, "sigma_t": 2.0,
                          "density": {"fbm": {"octaves": 2}}}]}
    out = tv.render(scene)
    for x in (out.radiance, out.depth, out.alpha, *out.aovs.values()):
        assert bool(torch.isfinite(x).all())
