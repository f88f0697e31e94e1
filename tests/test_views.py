"""Multi-view samples (`[dataset] views`) and the volume as a label (`[dataset] volume_label`):
shapes, one batch, kornia-consistent cameras, the extinction grid rendered back, files round trip."""

import importlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from kornia.geometry.depth import depth_to_3d_v2

import torchvol as tv
from torchvol.dataset.datasets import collate, render_samples
from torchvol.dataset.generate import generate
from torchvol.dataset.recipe import render_seed
from torchvol.dataset.views import view_params
from torchvol.dataset.volume_label import extinction_grid, grid_scene
from torchvol.fields.grid import sample_grid

ROOT = Path(__file__).resolve().parents[1]
CLOUDS = ROOT / "datasets" / "clouds.toml"
VIEWS = ROOT / "datasets" / "cloud-views.toml"
TINY = {"image.width": 16, "image.height": 12, "march.steps": 8}

# A near-opaque homogeneous sphere (mean free path 0.005) seen by cameras orbiting it: its depth is
# its surface to within ~1/σ.
SPHERE = {
    "dataset": {"views": 4, "volume_label": {"resolution": 16}},
    "image": {"width": 32, "height": 32},
    "camera": {"eye": {"orbit": {"center": [0.2, 0.1, 0.0], "distance": [3.0, 3.6], "elevation": [-20, 40]}},
               "target": [0.2, 0.1, 0.0], "fov_y": {"uniform": [40, 50]}},
    "lights": [{"kind": "sun", "direction": [1, 1, -0.5]}],
    "volumes": [{"bounds": {"sphere": {"center": [0.2, 0.1, 0.0], "radius": 1.0}}, "density": {"constant": 1.0},
                 "sigma_t": 200.0, "albedo": 0.9}],
}


def world_points(depth, K, world_to_camera):
    """Per-view world points (V, H, W, 3) of depths (V, 1, H, W) with kornia's unprojection."""
    cam = depth_to_3d_v2(depth[:, 0], K)  # (V, H, W, 3) camera frame
    to_world = torch.linalg.inv(world_to_camera)
    return torch.einsum("vij,vhwj->vhwi", to_world[:, :3, :3], cam) + to_world[:, None, None, :3, 3]


def test_views_one_keeps_todays_shapes_and_values():
    recipe = tv.Recipe.load(CLOUDS, TINY)
    item = render_samples(recipe, [2])[0]
    assert item["image"].shape == (3, 12, 16) and item["depth"].shape == item["alpha"].shape == (1, 12, 16)
    assert item["K"].shape == (3, 3) and item["world_to_camera"].shape == (4, 4)
    assert "extinction" not in item and "views" not in item["params"]
    alone = tv.render(recipe.sample(2), seed=render_seed(2, 0))
    for key in ("image", "depth", "alpha"):
        assert torch.equal(item[key], getattr(alone, key)[0]), key
    assert torch.equal(item["K"], alone.camera.K[0].float())


def test_views_render_as_one_batch_equal_to_each_view_alone(monkeypatch):
    recipe = tv.Recipe.load(CLOUDS, {**TINY, "dataset.views": 4})
    calls = []
    module = importlib.import_module("torchvol.renderer.executor")  # tv.render is the function
    real = module.render
    monkeypatch.setattr(module, "render", lambda scenes, **kw: calls.append(len(scenes)) or real(scenes, **kw))
    items = render_samples(recipe, [1, 3])
    assert calls == [8]  # two samples × four views: one batch
    assert collate(items)["image"].shape == (2, 4, 3, 12, 16)
    item = items[0]
    assert item["image"].shape == (4, 3, 12, 16) and item["depth"].shape == item["alpha"].shape == (4, 1, 12, 16)
    assert item["K"].shape == (4, 3, 3) and item["world_to_camera"].shape == (4, 4, 4)
    assert item["depth_median"].shape == (4, 1, 12, 16)
    per_view = view_params(recipe, 1, 0)
    for v, params in enumerate(per_view):
        alone = real(recipe._scene(params), seed=render_seed(1, 0))
        for key in ("image", "depth", "alpha"):
            assert torch.equal(item[key][v], getattr(alone, key)[0]), (key, v)
        assert torch.equal(item["world_to_camera"][v], alone.camera.world_to_camera[0].float())
    # only the camera differs between views; view 0 is the single-view sample
    assert all(p["volumes[0].sigma_t"] == per_view[0]["volumes[0].sigma_t"] for p in per_view)
    assert len({tuple(p["camera.eye"]) for p in per_view}) == 4
    assert per_view[0] == tv.Recipe.load(CLOUDS, TINY).sample_params(1, 0)
    assert item["params"]["views"] == [{"camera.eye": p["camera.eye"], "camera.fov_y": p["camera.fov_y"]} for p in per_view]


def test_four_views_unproject_onto_one_sphere():
    """Each view's depth, unprojected with kornia, lies on the sphere; a point of view a visible
    from view b projects into b at b's depth there."""
    recipe = tv.Recipe.load(SPHERE)
    item = render_samples(recipe, [0])[0]
    depth, K, w2c = item["depth"], item["K"], item["world_to_camera"]
    hit = depth[:, 0] > 0
    assert hit.float().mean() > 0.15
    points = world_points(depth, K, w2c)
    centre = torch.tensor([0.2, 0.1, 0.0])
    radius = (points[hit] - centre).norm(dim=-1)
    assert (radius - 1.0).abs().max() < 0.02, (radius - 1.0).abs().max()
    eyes = torch.linalg.inv(w2c)[:, :3, 3]
    checked = 0
    for a in range(4):
        p = points[a][hit[a]]
        for b in range(4):
            if a == b:
                continue
            normal = (p - centre) / (p - centre).norm(dim=1, keepdim=True)
            toward = eyes[b] - p
            facing = (normal * toward).sum(1) / toward.norm(dim=1) > 0.5  # well inside b's visible side
            cam = p[facing] @ w2c[b, :3, :3].T + w2c[b, :3, 3]
            uv = cam @ K[b].T
            uv = uv[:, :2] / uv[:, 2:]
            inside = (uv >= 0.5).all(1) & (uv[:, 0] <= 30.5) & (uv[:, 1] <= 30.5)
            grid = torch.stack([(uv[inside, 0] + 0.5) / 16 - 1, (uv[inside, 1] + 0.5) / 16 - 1], dim=1)
            seen = F.grid_sample(depth[b:b + 1], grid[None, None], align_corners=False)[0, 0, 0]
            err = (seen - cam[inside, 2]).abs()
            assert err.numel() == 0 or err.max() < 0.015, (a, b, err.max())
            checked += err.numel()
    assert checked > 200


def test_cloud_views_unproject_inside_the_labelled_volume():
    """The four views of a cloud unproject (kornia) into the extinction label's box, onto cells
    the label says hold medium."""
    recipe = tv.Recipe.load(VIEWS, {"image.width": 24, "image.height": 24, "march.steps": 16,
                                    "dataset.volume_label.resolution": 16})
    item = render_samples(recipe, [0])[0]
    ext, box = item["extinction"], item["extinction_box"]
    assert ext.shape == (16, 16, 16) and ext.dtype == torch.float32 and box.shape == (2, 3)
    hit = item["depth"][:, 0] > 0
    assert all(hit[v].any() for v in range(4))
    p = world_points(item["depth"], item["K"], item["world_to_camera"])[hit]
    assert ((p >= box[0]) & (p <= box[1])).all()
    sigma = sample_grid(ext, box[0], box[1], p)
    assert (sigma > 0).float().mean() > 0.95, (sigma > 0).float().mean()


def test_extinction_of_a_constant_box_is_sigma_t_exactly():
    scene = {"volumes": [{"bounds": {"box": {"min": [-1, -0.5, 0], "max": [1, 0.5, 2]}}, "density": {"constant": 0.5},
                          "sigma_t": 6.0}]}
    ext, box = extinction_grid(scene, 8)
    assert torch.equal(ext, torch.full((8, 8, 8), 3.0))
    assert torch.equal(box, torch.tensor([[-1.0, -0.5, 0.0], [1.0, 0.5, 2.0]]))


def test_extinction_convention_and_union_of_volumes():
    """[k, j, i] is the centre of cell (i, j, k); two volumes sum on the union of their boxes."""
    slab_x = np.zeros((4, 4, 4))
    slab_x[:, :, 3] = 1.0  # the cells of largest x
    scene = {"volumes": [
        {"bounds": {"box": {"min": [0, 0, 0], "max": [4, 4, 4]}}, "density": {"grid": {"data": slab_x}}, "sigma_t": 2.0},
        {"bounds": {"box": {"min": [0, 0, 4], "max": [4, 4, 8]}}, "density": {"constant": 1.0}, "sigma_t": 5.0},
    ]}
    ext, box = extinction_grid(scene, 4)
    assert torch.equal(box, torch.tensor([[0.0, 0, 0], [4, 4, 8]]))
    # cells are 1 × 1 × 2: centres x = i + 0.5, z = 2k + 1; the first box covers k = 0, 1
    assert torch.equal(ext[2:], torch.full((2, 4, 4), 5.0))
    expected = torch.tensor([0.0, 0.0, 0.0, 2.0])  # the label's cell centres along x are the grid's
    assert torch.allclose(ext[:2], expected.expand(2, 4, 4))


def test_slab_bounds_are_refused():
    scene = {"volumes": [{"bounds": {"slab": {"y_min": 0, "y_max": 1}}, "density": {"constant": 1.0}}]}
    with pytest.raises(ValueError, match=r"dataset.volume_label.*volumes\[0\] has slab bounds"):
        extinction_grid(scene, 8)
    with pytest.raises(ValueError, match=r"dataset.volume_label.*volumes\[0\] has slab bounds"):
        tv.Recipe.load({**scene, "dataset": {"volume_label": {"resolution": 8}}})


SPHERE_SCENE = {"image": {"width": 32, "height": 32}, "camera": {"eye": [0.4, 1.2, -3.2], "fov_y": 50},
                "lights": [{"kind": "sun", "direction": [1, 1, -0.5], "shadow": {"steps": 8}}],
                "volumes": [{"bounds": {"sphere": {"center": [0.1, 0, 0], "radius": 1.0}}, "density": {"constant": 1.0},
                             "sigma_t": 2.0, "albedo": 0.9}]}


def cloud_scene():
    return tv.Recipe.load(CLOUDS, {"image.width": 32, "image.height": 32}).sample(1)


# Mean |alpha(label rendered back) − alpha(scene)| over 32×32 pixels, measured: homogeneous sphere
# 0.0192 (N = 16), 0.0086 (N = 32); fbm cloud (clouds.toml sample 1) 0.0214, 0.0059. The error is the
# grid's: trilinear cells blur the sphere's edge (O(1/N)) and the cloud's detail.
@pytest.mark.parametrize("name, n, bound", [("sphere", 16, 0.03), ("sphere", 32, 0.012),
                                            ("cloud", 16, 0.03), ("cloud", 32, 0.009)])
def test_extinction_grid_rendered_back_reproduces_alpha(name, n, bound):
    scene = SPHERE_SCENE if name == "sphere" else cloud_scene()
    reference = tv.render(scene)
    ext, box = extinction_grid(scene, n)
    back = tv.render(grid_scene(scene, ext, box))
    assert "volume0.march" in back.stats["passes"]
    err = (back.alpha - reference.alpha).abs().mean().item()
    assert err < bound, err


def test_recipe_keys_are_validated():
    for overrides, needle in [
        ({"dataset.views": 0}, "dataset.views: got 0"),
        ({"dataset.views": 2.0}, "dataset.views: got 2.0"),
        ({"dataset.volume_label": 32}, "dataset.volume_label: got 32; expected a table"),
        ({"dataset.volume_label": {"resolution": 1}}, "dataset.volume_label.resolution: got 1"),
        ({"dataset.volume_label": {"resolutoin": 8}}, "dataset.volume_label: got"),
    ]:
        with pytest.raises(ValueError, match=needle.replace(".", r"\.").replace("(", r"\(")):
            tv.Recipe.load(CLOUDS, overrides)
    fixed = {"image": {"width": 8, "height": 8}, "dataset": {"views": 2},
             "volumes": [{"bounds": {"sphere": {"center": [0, 0, 0], "radius": 1}}, "density": {"constant": 1}}]}
    with pytest.raises(ValueError, match=r"dataset\.views: got 2; every view would be the same"):
        tv.Recipe.load(fixed)


@pytest.mark.parametrize("layout", ["folder", "webdataset"])
def test_files_round_trip(tmp_path, layout):
    overrides = {**TINY, "dataset.views": 3, "dataset.volume_label": {"resolution": 8}}
    out = tmp_path / "ds"
    generate(CLOUDS, count=2, out=out, overrides=overrides, layout=layout, batch=2)
    records = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
    live = tv.SceneDataset(CLOUDS, 2, overrides=overrides)
    meta = json.loads((out / "meta.json").read_text())
    assert meta["views"] == 3 and meta["volume_label"]["resolution"] == 8 and "[k, j, i]" in meta["volume_label"]["convention"]
    rec, item = records[1], live[1]
    assert torch.equal(torch.tensor(rec["K"]), item["K"]) and torch.equal(torch.tensor(rec["world_to_camera"]), item["world_to_camera"])
    if layout == "webdataset":
        assert rec["files"]["image"] == ["000001.image.0.png", "000001.image.1.png", "000001.image.2.png"]
        wds = pytest.importorskip("webdataset")
        shard = str(next((out / "shards").glob("*.tar")))
        sample = list(wds.WebDataset(shard, shardshuffle=False).decode("torchrgb"))[1]
        for v in range(3):  # each member decodes by its last extension
            assert torch.equal(torch.as_tensor(sample[f"depth.{v}.npy"]), item["depth"][v, 0])
            assert (sample[f"image.{v}.png"] - item["image"][v]).abs().max() <= 0.5 / 255 + 1e-6
        assert torch.equal(torch.as_tensor(sample["extinction.npy"]), item["extinction"])
        return
    back = tv.FolderDataset(out)[1]
    assert back.keys() == item.keys()
    for key in ("depth", "depth_median", "K", "world_to_camera", "extinction", "extinction_box"):
        assert back[key].shape == item[key].shape and torch.equal(back[key], item[key]), key
    for key in ("image", "alpha"):  # 8-bit PNG
        assert back[key].shape == item[key].shape and (back[key] - item[key]).abs().max() <= 0.5 / 255 + 1e-6, key
    assert back["params"] == item["params"]
