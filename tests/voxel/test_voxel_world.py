"""The voxel-world recipe (water, specular and emissive samples), the terrain's `ores`, and issue 14's
hard cases that other tests leave out: a camera exactly on the water plane, a camera under water
(Beer-Lambert against a dry render), a point light inside a closed room with GI (I·cosθ/r² on the
walls, GI bounded). Roughness 0 and 1 are in test_ggx.py's furnace and finiteness tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import assert_close
from hypothesis import given, settings
from hypothesis import strategies as st

import torchvol as tv
from torchvol.dataset.datasets import render_samples
from torchvol.scene.model import Voxels
from torchvol.voxel.grid import (
    _cells,
    cell_range,
    dense_materials,
    terrain_height,
    terrain_materials,
)

pytestmark = pytest.mark.usefixtures("one_thread")
F64 = torch.float64
RECIPE = Path(__file__).resolve().parents[2] / "datasets" / "voxel-world.toml"


def pixel_rays(out):
    """World eye [3] and unit ray directions (H, W, 3) through the pixel centres of `out`'s camera."""
    cam = out.camera
    v, u = torch.meshgrid(torch.arange(cam.height, dtype=F64), torch.arange(cam.width, dtype=F64), indexing="ij")
    d_cam = torch.stack([u, v, torch.ones_like(u)], dim=-1) @ torch.linalg.inv(cam.K[0].double()).T
    c2w = cam.camera_to_world[0].double()
    d = d_cam @ c2w[:3, :3].T
    return c2w[:3, 3], d / d.norm(dim=-1, keepdim=True)


def hit_distance(out, d):
    """Distance (H, W) along the unit rays d (H, W, 3) from the planar depth of `out`."""
    return out.depth[0, 0].double() / (d @ out.camera.world_to_camera[0, 2, :3].double())


# -- terrain ores ----------------------------------------------------------------------------------


def terrain(**ores) -> Voxels:
    return Voxels.model_validate({"occupancy": {"terrain": {"seed": 3, "amplitude": 6.0, "ores": ores}},
                                  "cells": {"min": [-12, -6, -12], "max": [12, 8, 12]}})


def test_ores_are_sparse_hashed_blocks_near_the_surface():
    spec = terrain(material=4, density=0.1, seed=5, depth=1.0)
    grid = dense_materials(spec)
    lo, hi = cell_range(spec)
    cells = _cells(lo, hi, "cpu")
    assert torch.equal(grid.reshape(-1).long(), terrain_materials(cells, spec.occupancy.terrain)), "both paths agree"
    h = terrain_height(cells[:, 0].float(), cells[:, 2].float(), spec.occupancy.terrain)
    ore = grid.reshape(-1) == 4
    top = (cells[:, 1] <= h) & (cells[:, 1] > h - 1.0)
    assert bool((~ore | top).all()), "ores only within `depth` under the surface, never in the air"
    assert 0.07 < ore.sum().item() / top.sum().item() < 0.13, "about `density` of those cells"
    plain = dense_materials(Voxels.model_validate({**spec.model_dump(), "occupancy": {"terrain": {"seed": 3, "amplitude": 6.0}}}))
    assert torch.equal(torch.where(grid == 4, plain, grid), plain), "the layers elsewhere unchanged"
    assert torch.equal(dense_materials(spec), grid), "deterministic"
    assert not torch.equal(dense_materials(terrain(material=4, density=0.1, seed=6)), grid), "the seed moves them"
    deeper = dense_materials(terrain(material=4, density=0.1, seed=5, depth=3.0)) == 4
    assert deeper.sum() > ore.sum() and bool((deeper.reshape(-1) | ~ore).all()), "a deeper band holds the same and more"
    assert torch.equal(dense_materials(terrain(material=4, density=0.0)), plain)


def test_bad_ores_are_refused_naming_the_key():
    for key, value in (("density", 1.5), ("material", 0), ("depth", 0.0)):
        with pytest.raises(ValueError, match=f"voxels.occupancy.terrain.ores.{key}"):
            tv.load_scene({"voxels": {"occupancy": {"terrain": {"ores": {key: value}}}}})


# -- the recipe --------------------------------------------------------------------------------------


def test_voxel_world_samples_show_water_specular_and_emission():
    recipe = tv.Recipe.load(RECIPE, {"image.width": 24, "image.height": 24})
    params = [recipe.sample_params(i) for i in range(8)]
    materials = [recipe.sample(i).voxels.materials for i in range(8)]
    shiny = [any(m.metallic > 0.5 or m.roughness < 0.3 for m in ms[:3]) for ms in materials]
    assert 2 <= sum(shiny) <= 8, "some worlds hold metal or polished layers"
    assert all(max(ms[3].emission) > 1.0 for ms in materials) and all(p["voxels.occupancy.terrain.ores.density"] > 0
                                                                        for p in params), "lamps in every world"
    assert len({p["voxels.occupancy.terrain.seed"] for p in params}) == 8 and len({str(p["voxels.gi"]) for p in params}) > 1
    items = render_samples(recipe, range(4))
    seen = {"water": 0, "specular": 0, "lamp": 0}
    for item in items:
        for key in ("image", "depth", "normal", "roughness", "metallic", "water", "water_floor_distance", "ao", "shadow"):
            assert torch.isfinite(item[key]).all(), key
        assert 0.05 < item["image"].mean() < 0.9, "not black, not saturated"
        seen["water"] += bool((item["water"] > 0).any())
        seen["specular"] += bool(((item["metallic"] > 0.5) | ((item["roughness"] < 0.3) & (item["material"] > 0))).any())
        seen["lamp"] += bool((item["material"] == 4).any())
    assert all(seen.values()), seen


# -- hard cases: the water plane ------------------------------------------------------------------


def shore(eye_y: float, *, pitch: float = 0.0, water: bool = True, size=(9, 9)) -> dict:
    """A voxel island seen from outside its grid, the camera at height eye_y looking along +z,
    tilted by `pitch` (the target's height per unit ahead); water at y = 0."""
    scene = {"image": {"width": size[0], "height": size[1]},
             "camera": {"eye": [0.3137, eye_y, -14.21], "target": [0.3137, eye_y + 14.21 * pitch, 0.0], "fov_y": 60.0},
             "sky": {"kind": "gradient", "horizon": [0.7, 0.8, 0.9], "slope": [-0.2, -0.1, 0.0]},
             "lights": [{"kind": "sun", "direction": [0.3, 0.8, -0.4]}],
             "voxels": {"occupancy": {"terrain": {"seed": 2, "base": -3.0, "amplitude": 6.0, "frequency": 0.15, "octaves": 2}},
                        "cells": {"min": [-8, -4, -8], "max": [8, 5, 8]}, "max_steps": 48, "reflections": {"bounces": 1},
                        "materials": [{"color": [0.4, 0.7, 0.3], "roughness": 0.2}, [0.6, 0.5, 0.3], [0.5, 0.5, 0.5]]}}
    if water:
        scene["voxels"]["water"] = {"level": 0.0, "waves": {"amplitude": 0.05}}
    return scene


def test_camera_exactly_on_the_water_plane_looking_along_it():
    """Rays from a camera exactly at the water level: upward ones see what they see without water
    (bitwise), downward ones enter the water where the camera stands: the render is the limit of a
    camera just above, not a world without water."""
    on = tv.render(shore(0.0), dtype=F64)
    above = tv.render(shore(1e-12), dtype=F64)
    dry = tv.render(shore(0.0, water=False), dtype=F64)
    _, d = pixel_rays(on)
    up, down = d[..., 1] > 0, d[..., 1] < 0
    for out in (on, above):
        assert torch.isfinite(out.radiance).all() and torch.isfinite(out.depth).all()
        assert bool((out.aovs["water"][0, 0][down] == 1).all()) and bool((out.aovs["water"][0, 0][up] == 0).all())
    assert torch.equal(on.radiance[0][:, up], dry.radiance[0][:, up])
    assert_close(on.radiance, above.radiance, atol=1e-6, what="on the plane = just above it")
    assert_close(on.depth[0, 0][down], torch.zeros_like(on.depth[0, 0][down]), atol=0.0, what="water at the eye")


@settings(max_examples=20, deadline=None)
@given(eye_y=st.sampled_from([0.0, 1e-12, -1e-12, 1e-7, -1e-7, 0.01, -0.01]),
       pitch=st.one_of(st.just(0.0), st.floats(-0.3, 0.3)), dtype=st.sampled_from([torch.float32, F64]))
def test_near_the_water_plane_everything_is_finite(eye_y, pitch, dtype):
    out = tv.render(shore(eye_y, pitch=pitch, size=(6, 5)), dtype=dtype)
    assert torch.isfinite(out.radiance).all() and torch.isfinite(out.depth).all()
    assert all(torch.isfinite(v).all() for v in out.aovs.values())


def test_camera_under_water_sees_voxels_attenuated_by_beer_lambert():
    """A camera under water looking down at a voxel floor (lit by ambient only, no ray meets the
    surface): each pixel is the dry render's radiance times e^{−a·t}, t the distance to the hit."""
    a = [0.3, 0.15, 0.05]

    def scene(water):
        s = {"image": {"width": 11, "height": 9},
             "camera": {"eye": [0.3, -1.0, 0.2], "target": [0.0, -5.0, 1.0], "fov_y": 70.0},
             "voxels": {"occupancy": {"grid": {"data": np.ones((12, 1, 12), np.uint8)}},
                        "cells": {"min": [-6, -6, -6], "max": [6, -5, 6]}, "materials": [[0.8, 0.6, 0.4]],
                        "ambient": [0.9, 0.9, 0.9], "ao": {"gamma": 1.0}}}
        if water:
            s["voxels"]["water"] = {"level": 0.0, "absorption": a}
        return s

    wet, dry = tv.render(scene(True), dtype=F64), tv.render(scene(False), dtype=F64)
    assert bool((dry.alpha > 0).all()), "the floor fills the view"
    _, d = pixel_rays(dry)
    t = hit_distance(dry, d)
    want = dry.radiance[0] * torch.exp(-torch.tensor(a, dtype=F64)[:, None, None] * t)
    assert_close(wet.radiance[0].double(), want, atol=1e-6, what="Beer-Lambert under water (float32 outputs)")
    assert (wet.aovs["water"] == 0).all() and (wet.radiance < dry.radiance).all()


# -- hard cases: a point light inside a closed room with GI ------------------------------------------


def lit_room(light, *, gi=None, albedo=0.6, size=(9, 7)) -> dict:
    """A closed box room (inner cells x, z ∈ [−3, 3), y ∈ [−2, 2)), the camera inside, lit only by a
    shadowed point light."""
    shell = {"subtraction": {"a": {"box": {"center": [0.0, 0.0, 0.0], "half_size": [5.0, 4.0, 5.0]}},
                             "b": {"box": {"center": [0.0, 0.0, 0.0], "half_size": [3.0, 2.0, 3.0]}}}}
    return {"image": {"width": size[0], "height": size[1]},
            "camera": {"eye": [0.3, 0.2, -0.6], "target": [0.0, -0.3, 2.0], "fov_y": 100.0},
            "lights": [{"kind": "point", "position": light, "intensity": 3.0, "shadow": {"steps": 32}}],
            "voxels": {"occupancy": {"sdf": {"shape": shell, "material": 1}}, "cells": {"min": [-6, -6, -6], "max": [6, 6, 6]},
                       "materials": [[albedo] * 3], "ambient": [0.0, 0.0, 0.0], "face_tones": [1.0, 1.0, 1.0],
                       "shadow": {"steps": 32}, **({} if gi is None else {"gi": gi})}}


@pytest.mark.parametrize("light", [[0.5, 0.7, 1.1], [1.0, 1.0, 1.0], [0.2, -1.9999, 0.4]],
                         ids=["inside", "on a cell corner", "1e-4 above the floor"])
def test_a_point_light_in_a_closed_room_lights_the_walls_by_i_cos_over_r2_and_gi_stays_bounded(light):
    """Without GI each wall pixel is albedo · I · cos θ / r² (every wall sees the light in a convex
    room: the shadow ray stops at the light, not at the wall behind it). With GI the image is finite
    and lies between that and the bound of a closed room: L_indirect ≤ a² E_max / (1 − a)."""
    a, intensity = 0.6, 3.0
    direct = tv.render(lit_room(light), dtype=F64)
    eye, d = pixel_rays(direct)
    normal = direct.aovs["normal"][0].permute(1, 2, 0).double()
    x = eye + hit_distance(direct, d)[..., None] * d
    x = torch.where(normal != 0, x.round(), x)  # onto the face's integer plane: float32 depths would blur cos θ at grazing light
    to_light = torch.tensor(light, dtype=F64) - x
    r2 = (to_light * to_light).sum(-1)
    cos = (normal * to_light).sum(-1) / r2.sqrt()
    want = a * intensity * cos.clamp_min(0.0) / r2
    # relative: outputs are float32, and near the light the hit position's rounding is amplified by 1/r²
    relative = (direct.radiance[0].double() - want) / want.clamp_min(1e-3)
    assert_close(relative, torch.zeros_like(relative), atol=1e-4, what="a·I·cosθ/r² (relative)")
    out = tv.render(lit_room(light, gi={"method": "path", "bounces": 2, "samples": 4}), dtype=F64)
    assert torch.isfinite(out.radiance).all() and "voxels.gi" in out.stats["passes"]
    gap = min(abs(light[1] + 2.0), abs(light[1] - 2.0), *(abs(c + s * 3.0) for c in (light[0], light[2]) for s in (1, -1)))
    bound = a * a * intensity / gap**2 / (1.0 - a)
    indirect = out.radiance - direct.radiance
    assert bool((indirect >= -1e-12).all()) and bool((indirect <= bound).all()) and bool((indirect > 0).any())
