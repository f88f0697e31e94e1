"""Voxel scenes through tv.render: AOVs and passes only when called for, occupancy kinds agree,
volumes composite over the surface and stop at it, depth is the surface's planar z, batching,
validation messages name the key path."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import assert_close

import torchvol as tv
from torchvol.voxel.grid import terrain_height, terrain_materials

pytestmark = pytest.mark.usefixtures("one_thread")  # small ops: threads only add overhead


def wall_scene(**voxels):
    """A camera at z = -5 looking along +z at an 8×8 wall of cells z = 3 (world z in [3, 4))."""
    data = np.ones((1, 8, 8), dtype=np.uint8)
    return {
        "image": {"width": 12, "height": 10},
        "camera": {"eye": [0.0, 0.0, -5.0], "target": [0.0, 0.0, 0.0], "fov_y": 30.0},
        "lights": [{"direction": [0.3, 0.5, -1.0], "intensity": 0.5}],
        "voxels": {"occupancy": {"grid": {"data": data}}, "cells": {"min": [-4, -4, 3]}, **voxels},
    }


def test_only_computed_aovs_and_passes():
    out = tv.render(wall_scene())
    assert set(out.aovs) == {"normal", "uv"}
    assert out.stats["passes"] == ["rays", "voxels.dda", "voxels.shade", "composite"]
    out = tv.render(wall_scene(ao={"gamma": 0.5}, shadow={"steps": 8}, materials=[[1, 0, 0], [0, 1, 0]]))
    assert set(out.aovs) == {"normal", "uv", "ao", "shadow", "material"}
    assert out.stats["passes"] == ["rays", "voxels.dda", "voxels.shade", "voxels.ao", "voxels.shadow0", "composite"]


def test_wall_depth_normal_alpha():
    out = tv.render(wall_scene())
    assert out.alpha.min().item() == 1.0  # the wall fills the view
    assert_close(out.depth[0, 0], torch.full((10, 12), 8.0), atol=1e-5, what="planar depth of the wall at z = 3")
    n = out.aovs["normal"][0]
    assert torch.equal(n, torch.tensor([0.0, 0.0, -1.0])[:, None, None].expand(3, 10, 12))
    uv = out.aovs["uv"]
    assert uv.min() >= 0 and uv.max() <= 1


def test_occupancy_kinds_agree():
    """The same cells as a grid, a function and an sdf box give the same image."""
    a = tv.render(wall_scene()).image
    fn = lambda c: ((c[:, 2] == 3) & (c[:, 0] >= -4) & (c[:, 0] < 4) & (c[:, 1] >= -4) & (c[:, 1] < 4)).long()
    s = wall_scene()
    s["voxels"].update(occupancy={"function": {"fn": fn}}, cells={"min": [-4, -4, 0], "max": [4, 4, 6]})
    b = tv.render(s).image
    s["voxels"].update(occupancy={"sdf": {"shape": {"box": {"center": [0, 0, 3.5], "half_size": [4, 4, 0.5]}}}})
    c = tv.render(s).image
    assert torch.equal(a, b) and torch.equal(a, c)


def test_volume_in_front_composites_and_volume_behind_is_cut():
    sigma = 0.7
    vol = {"bounds": {"box": {"min": [-3, -3, 0.0], "max": [3, 3, 1.0]}}, "density": {"constant": 1.0},
           "sigma_t": sigma, "albedo": 0.0}
    s = wall_scene()
    surf = tv.render(s)
    s["volumes"] = [vol]
    out = tv.render(s)
    assert out.alpha.min().item() == 1.0
    ratio = (out.radiance / surf.radiance.clamp_min(1e-9))[0, 0]
    # an absorbing slab: radiance ≈ T · surface along each ray (chord 1 / forward_cos)
    rays = out.camera.rays()
    chord = 1.0 / rays.forward_cos.reshape(10, 12)
    assert_close(ratio, torch.exp(-sigma * chord).float(), atol=1e-4, what="transmitted surface radiance")
    # depth: (alpha·t_mean + T·t_surface)/(alpha + T), planar
    t_s = 8.0 * chord
    a = 1 - torch.exp(-sigma * chord)
    t0 = 5.0 * chord
    x = sigma * chord
    t_mean = t0 + chord * (1 / x - torch.exp(-x) / (1 - torch.exp(-x)))
    expected = (a * t_mean + (1 - a) * t_s) / chord * 1.0
    assert_close(out.depth[0, 0], expected.float(), atol=2e-4, what="composited depth")
    # a volume entirely behind the wall changes nothing
    s["volumes"] = [{**vol, "bounds": {"box": {"min": [-3, -3, 5.0], "max": [3, 3, 6.0]}}, "emission": [5.0, 5.0, 5.0]}]
    behind = tv.render(s)
    assert torch.equal(behind.radiance, surf.radiance) and torch.equal(behind.depth, surf.depth)


def test_batch_equals_single_renders():
    a = tv.preset("voxel-carved-box", width=24, height=16)
    b = tv.preset("voxel-carved-box", width=24, height=16, eye=(2.0, 4.0, -13.0), sun_dir=(0.3, 0.9, 0.2))
    both = tv.render([a, b])
    for i, s in enumerate((a, b)):
        one = tv.render(s)
        assert torch.equal(both.image[i], one.image[0]) and torch.equal(both.depth[i], one.depth[0])
        for k in one.aovs:
            assert torch.equal(both.aovs[k][i], one.aovs[k][0]), k


def test_terrain_layers():
    from torchvol.scene.model import TerrainOccupancy

    spec = TerrainOccupancy(amplitude=6.0, seed=2)
    x, z = torch.meshgrid(torch.arange(-8, 8), torch.arange(-8, 8), indexing="ij")
    x, z = x.reshape(-1), z.reshape(-1)
    h = terrain_height(x.float(), z.float(), spec)
    for y, want in ((torch.floor(h) + 1, 0), (torch.floor(h), 1)):
        cells = torch.stack([x, y.long(), z], dim=1)
        got = terrain_materials(cells, spec)
        exp = torch.where(y > h, 0, torch.where(y > h - 1, 1, 2))
        assert torch.equal(got, exp)
    deep = torch.stack([x, (torch.floor(h) - 10).long(), z], dim=1)
    assert (terrain_materials(deep, spec) == 3).all()


def test_texture_atlas_and_materials():
    atlas = np.zeros((4, 4, 3), dtype=np.uint8)
    atlas[:2, :2] = 255  # tile 0 (material 1) white, others black
    s = wall_scene(texture={"atlas": atlas, "tiles": 2}, face_tones=[1, 1, 1], ambient=[1, 1, 1])
    s["lights"] = []
    out = tv.render(s)
    assert_close(out.radiance, torch.ones_like(out.radiance), what="white tile")
    s["voxels"]["materials"] = [[1, 1, 1], [1, 1, 1]]
    s["voxels"]["occupancy"]["grid"]["data"] = np.full((1, 8, 8), 2, dtype=np.uint8)
    out = tv.render(s)
    assert out.radiance.max().item() == 0.0 and (out.aovs["material"] == 2).all()


@pytest.mark.parametrize("key,value,path", [
    ("voxels.max_steps", 0, "voxels.max_steps"),
    ("voxels.ao.gamma", -1.0, "voxels.ao.gamma"),
    ("voxels.occupancy.sdf.shape.subtraction.b.spher", {"radius": 1.0}, "voxels.occupancy.sdf.shape.subtraction.b.spher"),
    ("voxels.cells.max", [7, 7, -8], "voxels.cells"),
])
def test_validation_names_the_key(key, value, path):
    with pytest.raises(ValueError, match=path.replace(".", r"\.")):
        tv.load_scene("voxel-carved-box", overrides={key: value})


def test_grid_values_validated():
    s = wall_scene()
    s["voxels"]["occupancy"]["grid"]["data"] = np.full((1, 2, 2), 0.5)
    with pytest.raises(ValueError, match=r"voxels\.occupancy\.grid"):
        tv.load_scene(s)


def test_spp_resolves_surface_aovs():
    s = tv.load_scene(tv.preset("voxel-carved-box", width=24, height=16), overrides={"image.spp": 4})
    out = tv.render(s)
    a = out.alpha[0, 0]
    assert ((a > 0) & (a < 1)).any(), "silhouette pixels are partially covered"
    assert set(out.aovs) == {"normal", "ao", "shadow", "uv"}
    n = out.aovs["normal"][0]
    full = a == 1
    assert (n[:, full].abs().sum(0) <= 1 + 1e-6).all() and (out.depth[0, 0][a > 0] > 0).all()


def test_camera_inside_the_grid():
    s = wall_scene()
    s["voxels"]["cells"] = {"min": [-4, -4, -8]}
    s["voxels"]["occupancy"]["grid"]["data"] = np.concatenate([np.zeros((11, 8, 8), np.uint8), np.ones((1, 8, 8), np.uint8)])
    out = tv.render(s)  # camera at z = -5 inside the range [-8, 4): the wall at cell z = 3 as before
    assert_close(out.depth[0, 0], torch.full((10, 12), 8.0), atol=1e-5, what="depth from inside the grid")
