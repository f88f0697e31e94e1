"""Shadows and sky light through everything (issue 31, item 3): every light's shadow rays and every
sky-visibility ray see every volume, whatever its shading, and the terrain.

Closed forms in float64: a vertical ray through a homogeneous box is marched exactly (equal steps
over its chord of a constant σ_t), so a medium above another one dims what the lower one scatters
by exactly e^{−σ_t·h}, the σ_t × density of the `optical_thickness` label. Each ratio is of one
render against the same scene with the upper medium at σ_t = 0 (everything else, the camera rays
included, unchanged): in-scatter and the composite are linear in the light's transmittance.
"""

from __future__ import annotations

import math

import pytest
import torch
from conftest import assert_close
from hypothesis import given, settings
from hypothesis import strategies as st

import torchvol as tv
from torchvol.renderer import plan as plan_module
from torchvol.renderer.plan import make_plan

UP = [0.0, 1.0, 0.0]


def _box(lo, hi, sigma_t, **more) -> dict:
    return {"bounds": {"box": {"min": lo, "max": hi}}, "density": {"constant": 1.0}, "sigma_t": sigma_t, **more}


def _lit_box_under(upper: dict, **scene) -> dict:
    """A homogeneous scattering box at the origin seen from the side (the camera never sees `upper`,
    which lies above it, across every ray straight up from it), lit by a sun overhead."""
    return {
        "image": {"width": 12, "height": 10},
        "camera": {"eye": [0.0, 0.0, -5.0], "target": [0.0, 0.0, 0.0], "fov_y": 30.0},
        "volumes": [_box([-0.5, -0.5, -0.5], [0.5, 0.5, 0.5], 2.0, albedo=0.5), upper],
        **scene,
    }


def _ratio(scene_with: dict, scene_without: dict) -> tuple[torch.Tensor, object]:
    lit = tv.render(scene_with, dtype=torch.float64)
    bare = tv.render(scene_without, dtype=torch.float64)
    seen = bare.radiance[0, 1] > 1e-6
    assert seen.float().mean() > 0.1, "the lower box is in view and lit"
    return (lit.radiance[0, 1] / bare.radiance[0, 1].clamp_min(1e-300))[seen], lit


def test_a_shader_look_box_shadows_a_physical_one_by_its_exact_optical_depth(one_thread):
    """A sun straight overhead; above the lit box a shader-look box of σ_t 1.5, 0.8 thick: every
    shadow ray crosses 0.8 of it, the lower box's radiance is e^{−1.2} that of the same scene with
    the shader box at σ_t = 0 (before: the shader look cast no shadow, a ratio of 1)."""
    sigma, thick = 1.5, 0.8
    def scene(s):
        upper = _box([-1.0, 3.0, -1.0], [1.0, 3.0 + thick, 1.0], s, shading="shader")
        return _lit_box_under(upper, lights=[{"kind": "sun", "direction": UP, "intensity": 3.0, "shadow": {"steps": 8}}])
    ratio, out = _ratio(scene(sigma), scene(0.0))
    assert_close(ratio, torch.full_like(ratio, math.exp(-sigma * thick)), atol=1e-6, what="shadow through the shader look")
    assert "volume0.shadow0.volume1" in out.stats["passes"]
    assert make_plan(tv.load_scene(scene(sigma))).volumes[0].lights[0].occluders == (1,)


def test_ambient_visibility_sees_another_medium_by_its_exact_optical_depth(one_thread):
    """No light, only the lower box's sky light (`ambient`, visibility marched straight up): a
    pure absorber of σ_t 0.7 and 1.3 thick above it scales that sky light by e^{−0.91} (before:
    the visibility march saw its own volume only, a ratio of 1)."""
    sigma, thick = 0.7, 1.3
    def scene(s):
        upper = _box([-1.0, 3.0, -1.0], [1.0, 3.0 + thick, 1.0], s, albedo=0.0)
        out = _lit_box_under(upper)
        out["volumes"][0]["ambient"] = {"radiance": [1.0, 1.0, 1.0], "steps": 4}
        return out
    ratio, out = _ratio(scene(sigma), scene(0.0))
    assert_close(ratio, torch.full_like(ratio, math.exp(-sigma * thick)), atol=1e-6, what="sky light through the absorber")
    assert "volume0.ambient.volume1" in out.stats["passes"]
    sky = make_plan(tv.load_scene(scene(sigma))).volumes[0].ambient_sky
    assert sky.name == "volume0.ambient" and sky.light is None and sky.occluders == (1,) and not sky.terrain


def _ground_under(sigma: float, **terrain) -> dict:
    """Flat ground lit by its sky light only (no light), under a wide absorbing box 2 < y < 3.1
    that the camera, below it and looking down, never looks through onto the ground."""
    return {
        "image": {"width": 12, "height": 10},
        "camera": {"eye": [0.0, 1.0, -3.0], "target": [0.0, 0.0, 0.0], "fov_y": 40.0},
        "terrain": {"amplitude": 0.0, "ambient": [0.5, 0.6, 0.7], **terrain},
        "volumes": [_box([-500.0, 2.0, -500.0], [500.0, 3.1, 500.0], sigma, albedo=0.0)],
    }


def test_terrain_sky_light_is_dimmed_by_the_medium_above_it(one_thread):
    """The ground's radiance is its colour × its `ambient` × e^{−σ_t·1.1} under the box, by a
    ray straight up through it (before: the sky light was a constant, e^0)."""
    sigma = 0.9
    out = tv.render(_ground_under(sigma), dtype=torch.float64)
    ground = out.depth[0, 0] > 0
    assert ground.float().mean() > 0.5
    color, ambient = torch.tensor([0.3, 0.45, 0.18], dtype=torch.float64), torch.tensor([0.5, 0.6, 0.7], dtype=torch.float64)
    expected = (color * ambient * math.exp(-sigma * 1.1))[:, None].expand(3, int(ground.sum()))
    assert_close(out.radiance[0][:, ground], expected, atol=1e-6, what="the ground's sky light under the absorber")
    assert out.stats["passes"][:4] == ["rays", "terrain.trace", "terrain.shade", "terrain.ambient"]
    assert "terrain.ambient.volume0" in out.stats["passes"]


def test_terrain_sky_light_costs_nothing_where_not_asked_for(one_thread):
    """`ambient_visibility = "none"`, or no volume over the terrain: no visibility pass, the sky light
    is the constant `ambient`."""
    off = tv.load_scene(_ground_under(0.9, ambient_visibility="none"))
    bare = tv.load_scene({**_ground_under(0.9), "volumes": []})
    for scene in (off, bare):
        plan = make_plan(scene)
        assert plan.terrain.sky is None and not any("terrain.ambient" in n for n in plan.names())
    out = tv.render(off, dtype=torch.float64)
    ground = out.depth[0, 0] > 0
    assert_close(out.radiance[0, 1][ground], torch.full((int(ground.sum()),), 0.45 * 0.6, dtype=torch.float64), atol=1e-6)


def test_every_shadow_and_sky_ray_sees_every_volume_whatever_its_shading():
    """The plan: the terrain's shadow rays, its sky light and the sun-visibility label see the
    shader-look and surface-look volumes too; the sky light of a volume that reaches down among
    the hills sees the terrain."""
    scene = tv.load_scene({
        "lights": [{"kind": "sun", "direction": [0.3, 1.0, 0.2], "shadow": {"steps": 4}}],
        "terrain": {},
        "volumes": [_box([-1.0, 0.5, -1.0], [1.0, 3.0, 1.0], 1.0, ambient={"radiance": [1.0, 1.0, 1.0]}),
                    _box([-1.0, 4.0, -1.0], [1.0, 5.0, 1.0], 1.0, shading="shader"),
                    _box([-1.0, 6.0, -1.0], [1.0, 7.0, 1.0], 1.0, shading="surface")],
    })
    plan = make_plan(scene, aovs=["sun_visibility"])
    assert plan.terrain.shadows[0].occluders == (0, 1, 2) and plan.terrain.shadows[0].terrain
    assert plan.terrain.sky.occluders == (0, 1, 2) and not plan.terrain.sky.terrain
    assert plan.volumes[0].lights[0].occluders == (1, 2)
    assert plan.volumes[0].ambient_sky.occluders == (1, 2) and plan.volumes[0].ambient_sky.terrain
    assert plan.labels.sun.occluders == (0, 1, 2)


@pytest.mark.parametrize("low, direction, meets", [
    (2.5, [0.3, 1.0, 0.2], False),   # above every hill, the sun overhead: no ray of it descends
    (2.5, [0.3, 0.0, 0.2], False),   # a sun on the horizon: the rays stay level
    (2.5, [0.3, -0.2, 0.2], True),   # a sun below the horizon: the rays descend
    (1.5, [0.3, 1.0, 0.2], True),    # the box reaches down among the hills (base + amplitude = 2)
])
def test_a_volume_above_the_terrain_leaves_it_out_of_its_shadow_and_sky_rays(low, direction, meets, monkeypatch):
    """A volume wholly above the terrain's top, lit from at or above the horizon, traces no terrain
    on its shadow and sky rays (a ray that starts above a heightfield and never descends stays
    above it): the plan leaves the terrain out, and its image is bitwise the one that traces it."""
    scene = tv.load_scene({
        "image": {"width": 24, "height": 16},
        "camera": {"eye": [0.0, 3.0, -8.0], "target": [0.0, 1.5, 0.0]},
        "lights": [{"kind": "sun", "direction": direction, "shadow": {"steps": 4}}],
        "terrain": {"amplitude": 2.0},
        "volumes": [{"bounds": {"box": {"min": [-2.0, low, -2.0], "max": [2.0, low + 1.5, 2.0]}},
                     "density": {"fbm": {"octaves": 2}}, "sigma_t": 3.0,
                     "ambient": {"radiance": [0.3, 0.4, 0.5], "visibility": "march", "steps": 2}}],
        "march": {"quality": "draft"},
    })
    plan = make_plan(scene)
    assert plan.volumes[0].lights[0].terrain == meets
    assert plan.volumes[0].ambient_sky.terrain == (low < 2.0)
    outs = [tv.render(scene, compile=mode) for mode in ("off", "kernels")]
    assert ("volume0.shadow0.terrain" in outs[0].stats["time_s"]) == meets
    monkeypatch.setattr(plan_module, "meets_terrain", lambda batch, v, light: batch.terrain is not None)
    for out, mode in zip(outs, ("off", "kernels")):
        traced = tv.render(scene, compile=mode)
        assert "volume0.shadow0.terrain" in traced.stats["time_s"]
        assert torch.equal(out.radiance, traced.radiance), mode


@settings(max_examples=8, deadline=None)
@given(amplitude=st.floats(0.0, 3.0), above=st.floats(-0.5, 1.0), elevation=st.floats(-20.0, 85.0),
       azimuth=st.floats(0.0, 360.0))
def test_leaving_the_terrain_out_never_changes_a_value(amplitude, above, elevation, azimuth):
    """Any terrain height, any box height near its top, any sun: where the plan leaves the terrain
    out of the volume's shadow and sky rays, the image is bitwise the one that traces it."""
    e, a = math.radians(elevation), math.radians(azimuth)
    scene = tv.load_scene({
        "image": {"width": 16, "height": 12},
        "camera": {"eye": [0.0, amplitude + 3.0, -8.0], "target": [0.0, amplitude, 0.0]},
        "lights": [{"kind": "sun", "direction": [math.cos(e) * math.cos(a), math.sin(e), math.cos(e) * math.sin(a)],
                    "shadow": {"steps": 3}}],
        "terrain": {"amplitude": amplitude, "frequency": 0.8},
        "volumes": [{"bounds": {"box": {"min": [-3.0, amplitude + above, -3.0], "max": [3.0, amplitude + above + 1.0, 3.0]}},
                     "density": {"constant": 1.0}, "sigma_t": 1.5,
                     "ambient": {"radiance": [0.3, 0.4, 0.5], "visibility": "march", "steps": 2}}],
        "march": {"quality": "draft"},
    })
    out = tv.render(scene, compile="off")
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(plan_module, "meets_terrain", lambda batch, v, light: batch.terrain is not None)
        traced = tv.render(scene, compile="off")
    assert torch.equal(out.radiance, traced.radiance), float((out.radiance - traced.radiance).abs().max())


def voxel_floor_scene(volume, *, intensity=2.0, cells_min=(-4, 0, -4), cells_max=(4, 1, 4)):
    """A voxel slab (cells `cells_min`..`cells_max`) under an overhead shadowed sun, seen from the
    side below height 2, with `volume` in the scene."""
    return {"image": {"width": 32, "height": 16},
            "camera": {"eye": [0.0, 1.6, -9.0], "target": [0.0, 0.8, 0.0], "fov_y": 40.0},
            "lights": [{"kind": "sun", "direction": [0.0, 1.0, 0.0], "intensity": intensity, "shadow": {"steps": 4}}],
            "voxels": {"occupancy": {"function": {"fn": lambda cells: torch.ones(len(cells), dtype=torch.long)}},
                       "cells": {"min": list(cells_min), "max": list(cells_max)}, "materials": [[0.7, 0.7, 0.7]],
                       "shadow": {"steps": 16}},
            "volumes": [volume], "march": {"quality": "draft"}}


def test_voxel_shadow_rays_see_the_volumes(one_thread):
    # an absorbing box over the right half of a voxel floor, the sun overhead: the floor's direct
    # light under it is e^{−σ·thickness} of the light beside it (the view rays pass under the box)
    sigma, thickness = 1.3, 0.5
    box = {"bounds": {"box": {"min": [0.0, 2.0, -6.0], "max": [6.0, 2.0 + thickness, 6.0]}}, "sigma_t": sigma,
           "albedo": 0.0}
    lit, dark = tv.render(voxel_floor_scene(box)), tv.render(voxel_floor_scene(box, intensity=0.0))
    assert "voxels.shadow0.volume0" in lit.stats["passes"]
    floor = (lit.aovs["normal"][0, 1] > 0.99) & (lit.depth[0, 0] > 0)
    xs = world_x(lit)
    direct = (lit.radiance - dark.radiance)[0, 0]
    under, beside = floor & (xs > 0.5), floor & (xs < -0.5)
    assert under.sum() > 10 and beside.sum() > 10
    ratio = direct[under].mean() / direct[beside].mean()
    assert_close(ratio, math.exp(-sigma * thickness), atol=1e-4, what="floor under the box / beside it")


@pytest.mark.parametrize("compile", ["kernels", "off"])
def test_voxel_shadow_rays_cross_the_volumes_only_where_light_reaches(compile, one_thread):
    # a roof over the floor's left half and an absorbing slab high above both, out of the view: every
    # density evaluation is a shadow ray's, and only the faces the voxels leave lit send one (one
    # evaluation each: a constant's optical depth is closed-form)
    def floor_and_roof(cells):
        return ((cells[:, 1] == 0) | ((cells[:, 1] == 3) & (cells[:, 0] < 0))).long()

    scene = voxel_floor_scene({"bounds": {"box": {"min": [-8.0, 10.0, -8.0], "max": [8.0, 10.5, 8.0]}},
                               "sigma_t": 1.3, "albedo": 0.0}, cells_min=(-4, 0, -4), cells_max=(4, 4, 4))
    scene["voxels"]["occupancy"]["function"]["fn"] = floor_and_roof
    scene["camera"] = {"eye": [0.0, 6.0, -12.0], "target": [0.0, 0.0, 0.0], "fov_y": 40.0}
    out = tv.render(scene, aovs=["shadow"], compile=compile)
    surface, shadow = out.depth[0, 0] > 0, out.aovs["shadow"][0, 0]
    assert (surface & (shadow == 0)).sum() > 10 and (shadow > 0).sum() > 10  # faces under the roof, and lit ones
    assert out.stats["density_evals"] == int((shadow > 0).sum())


def test_volume_shadow_rays_see_the_voxels_without_a_terrain(one_thread):
    # a scattering layer under a voxel roof over its right half: no sun reaches it there
    layer = {"bounds": {"box": {"min": [-6.0, 0.0, -6.0], "max": [6.0, 1.0, 6.0]}}, "sigma_t": 0.5, "albedo": 1.0}
    out = tv.render(voxel_floor_scene(layer, cells_min=(0, 2, -6), cells_max=(6, 3, 6)))
    assert "volume0.shadow0.voxels" in out.stats["passes"]
    xs = world_x(out, fallback=True)
    mist = (out.aovs["normal"][0].abs().sum(dim=0) == 0) & (out.alpha[0, 0] > 0.5)  # the layer, no voxel face
    under, beside = mist & (xs > 1.0), mist & (xs < -1.0)
    assert under.sum() > 10 and beside.sum() > 10
    assert out.radiance[0, 0][under].max() < 1e-3 * out.radiance[0, 0][beside].mean()


@pytest.mark.parametrize("compile", ["kernels", "off"])
def test_volume_sky_light_sees_the_voxels(compile, one_thread):
    # the same layer and roof, lit by its sky light alone: the sky rays from under the roof meet it
    layer = {"bounds": {"box": {"min": [-6.0, 0.0, -6.0], "max": [6.0, 1.0, 6.0]}}, "sigma_t": 0.5, "albedo": 1.0,
             "ambient": {"radiance": [0.4, 0.4, 0.4], "visibility": "march", "steps": 2}}
    out = tv.render(voxel_floor_scene(layer, intensity=0.0, cells_min=(0, 2, -6), cells_max=(6, 3, 6)), compile=compile)
    assert "volume0.ambient.voxels" in out.stats["passes"]
    xs = world_x(out, fallback=True)
    mist = (out.aovs["normal"][0].abs().sum(dim=0) == 0) & (out.alpha[0, 0] > 0.5)
    under, beside = mist & (xs > 1.0), mist & (xs < -1.0)
    assert under.sum() > 10 and beside.sum() > 10
    assert out.radiance[0, 0][under].max() < 1e-3 * out.radiance[0, 0][beside].mean()


def world_x(out, fallback=False):
    """[H, W] world x of each pixel's depth point (with `fallback`, of its ray 9 units out)."""
    K, w2c = out.camera.K[0], out.camera.world_to_camera[0]
    h, w = out.depth.shape[-2:]
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    rays = torch.stack([u, v, torch.ones_like(u)], dim=-1) @ torch.linalg.inv(K).T @ w2c[:3, :3]
    eye = -w2c[:3, :3].T @ w2c[:3, 3]
    depth = out.depth[0, 0]
    if fallback:
        depth = torch.where(depth > 0, depth, torch.full_like(depth, 9.0))
    return (eye + depth[..., None] * rays)[..., 0]
