"""Sequences (`[dataset] frames`, `dt`, `camera_path`) and their flow (`torchvol.dataset.flow.flow_from_depth`).

Flow against closed forms (a fronto-parallel plane under sideways and forward camera motion), NaN-free
on hard depths, and against the renders themselves: frame f+1 warped back along the flow matches
frame f on a static terrain. Sequences are deterministic, frame 0 is the single-frame sample,
time advances the wind, and generated folders / shards read back equal.
"""

import json
import tarfile
from pathlib import Path

import pytest
import torch
from conftest import assert_close
from hypothesis import given, settings
from hypothesis import strategies as st
from kornia.geometry.transform import remap

import torchvol as tv
from torchvol.dataset.datasets import render_samples
from torchvol.dataset.flow import flow_from_depth
from torchvol.dataset.generate import generate
from torchvol.geometry.camera import Camera

ROOT = Path(__file__).resolve().parents[1]
CLOUDS = ROOT / "datasets" / "cloud-sequence.toml"
TINY = {"image.width": 16, "image.height": 12, "march.steps": 50, "dataset.frames": 3}


def _pinhole(B, H, W, f=20.0, dtype=torch.float64):
    K = torch.tensor([[f, 0.0, W / 2 - 0.5], [0.0, f, H / 2 - 0.5], [0.0, 0.0, 1.0]], dtype=dtype)
    return K.expand(B, 3, 3).clone()


def _translated(t, dtype=torch.float64):
    """world_to_camera of a camera with identity rotation whose eye is at `t` [B, 3]."""
    t = torch.as_tensor(t, dtype=dtype)
    M = torch.eye(4, dtype=dtype).repeat(t.shape[0], 1, 1)
    M[:, :3, 3] = -t
    return M


def test_sideways_translation_gives_minus_fx_tx_over_z():
    B, H, W = 3, 5, 7
    Z = torch.tensor([2.0, 5.0, 11.0], dtype=torch.float64)
    tx = torch.tensor([0.3, -0.7, 1.9], dtype=torch.float64)
    depth = Z[:, None, None, None].expand(B, 1, H, W).clone()
    K = _pinhole(B, H, W)
    K[:, 0, 0] = torch.tensor([20.0, 13.0, 31.0], dtype=torch.float64)  # fx != fy
    flow, valid = flow_from_depth(depth, K, _translated(torch.zeros(B, 3)), _translated(torch.stack([tx, 0 * tx, 0 * tx], -1)))
    assert flow.shape == (B, 2, H, W) and valid.shape == (B, 1, H, W) and valid.all()
    expected = (-K[:, 0, 0] * tx / Z)[:, None, None].expand(B, H, W)
    assert_close(flow[:, 0], expected, atol=1e-12, what="flow_x = -fx tx / Z")
    assert_close(flow[:, 1], torch.zeros(B, H, W, dtype=torch.float64), atol=1e-12, what="flow_y")


def test_forward_motion_expands_from_the_principal_point():
    """Moving forward by tz towards a plane at Z: u' − cx = (u − cx) Z / (Z − tz); behind the camera: invalid."""
    H, W, Z, tz = 6, 9, 4.0, 1.5
    depth = torch.full((1, 1, H, W), Z, dtype=torch.float64)
    K = _pinhole(1, H, W)
    flow, valid = flow_from_depth(depth, K, _translated([[0.0, 0.0, 0.0]]), _translated([[0.0, 0.0, tz]]))
    rows, cols = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    assert valid.all()
    assert_close(flow[0, 0], (cols - K[0, 0, 2]) * tz / (Z - tz), atol=1e-12, what="forward flow_x")
    assert_close(flow[0, 1], (rows - K[0, 1, 2]) * tz / (Z - tz), atol=1e-12, what="forward flow_y")
    # past the plane: every point is behind camera b
    flow, valid = flow_from_depth(depth, K, _translated([[0.0, 0.0, 0.0]]), _translated([[0.0, 0.0, Z + 1.0]]))
    assert not valid.any() and (flow == 0).all()


def test_rotated_cameras_agree_with_camera_project():
    """Flow from look_at cameras equals Camera.project of the unprojected points, minus the pixel."""
    H, W = 5, 8
    a = Camera.look_at([1.0, 2.0, -4.0], [0.0, 0.0, 0.0], [0, 1, 0], width=W, height=H, fov_y=50.0)
    b = Camera.look_at([1.6, 1.7, -3.5], [0.2, 0.1, 0.3], [0, 1, 0], width=W, height=H, fov_y=50.0)
    a, b = Camera(a.K.double(), a.world_to_camera.double(), W, H), Camera(b.K.double(), b.world_to_camera.double(), W, H)
    depth = torch.linspace(3.0, 6.0, H * W, dtype=torch.float64).reshape(1, 1, H, W)
    flow, valid = flow_from_depth(depth, a.K, a.world_to_camera, b.world_to_camera)
    rows, cols = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    cam = torch.stack([(cols - a.K[0, 0, 2]) / a.K[0, 0, 0], (rows - a.K[0, 1, 2]) / a.K[0, 1, 1], torch.ones_like(cols)], -1)
    world = (a.camera_to_world[0, :3, :3] @ (cam * depth[0, 0, ..., None]).reshape(-1, 3).T).T + a.camera_to_world[0, :3, 3]
    proj = b.project(world)
    assert valid.all()
    assert_close(flow[0, 0].reshape(-1), proj[:, 0] - cols.reshape(-1), atol=1e-9, what="flow_x")
    assert_close(flow[0, 1].reshape(-1), proj[:, 1] - rows.reshape(-1), atol=1e-9, what="flow_y")


@settings(max_examples=30, deadline=None)
@given(st.lists(st.sampled_from([0.0, -1.0, float("inf"), float("nan"), 1e-30, 0.5, 3.0, 1e6]), min_size=12, max_size=12),
       st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3))
def test_flow_is_nan_free_on_hard_depths(values, move):
    depth = torch.tensor(values, dtype=torch.float32).reshape(1, 1, 3, 4)
    flow, valid = flow_from_depth(depth, _pinhole(1, 3, 4, dtype=torch.float32), _translated([[0.0, 0.0, 0.0]], torch.float32),
                                  _translated([move], torch.float32))
    assert torch.isfinite(flow).all()
    good = torch.isfinite(depth) & (depth > 0)
    assert not (valid & ~good).any() and (flow * ~valid == 0).all()


def _terrain_sequence(**path):
    """A static sphere-traced terrain (nothing in it depends on time), smooth enough at 32x24 to
    interpolate, seen by a camera moving 1 s a frame along `path`."""
    return {
        "dataset": {"frames": 2, "dt": 1.0, "camera_path": path},
        "image": {"width": 32, "height": 24},
        "camera": {"eye": [0.0, 3.0, -6.0], "target": [0.0, 0.0, 0.0], "fov_y": 50.0},
        "sky": {"kind": "constant", "radiance": [0.5, 0.6, 0.8]},
        "lights": [{"kind": "sun", "direction": [0.6, 0.5, -0.3], "color": [1.0, 1.0, 1.0], "intensity": 1.0}],
        "terrain": {"seed": 3, "amplitude": 1.5, "frequency": 0.3, "octaves": 2, "steps": 96},
    }


def test_flow_warps_the_next_frame_onto_this_one():
    """Frame 1 sampled at pixel + flow (kornia remap): on valid, in-picture pixels it reproduces frame 0."""
    item = tv.SceneDataset(_terrain_sequence(velocity=[1.0, 0.2, 0.5], orbit=4.0, look_at="fixed"), 1)[0]
    flow, valid = item["flow"][0], item["flow_valid"][0, 0] > 0
    H, W = flow.shape[-2:]
    assert 1.0 < flow.norm(dim=0)[valid].mean() < 6.0 and valid.float().mean() > 0.5
    rows, cols = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")

    def warp_error(sign):
        x, y = cols + sign * flow[0], rows + sign * flow[1]
        # pixel maps (integer pixel centres): kornia's remap reads them with align_corners=True
        warped = remap(item["image"][1:], x[None], y[None], mode="bilinear", align_corners=True)[0]
        inside = valid & (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
        return (warped - item["image"][0]).abs().mean(0)[inside], (item["image"][1] - item["image"][0]).abs().mean(0)[inside]

    err, still = warp_error(1.0)
    # bilinear interpolation and disocclusions leave small errors; unwarped, the frames differ ~10x more
    assert err.median() < 0.25 * still.median() and err.mean() < 0.5 * still.mean(), (err, still)
    backwards, still = warp_error(-1.0)
    assert backwards.median() > still.median()  # the flow's sign matters


def test_sequence_shapes_determinism_and_frame_zero():
    recipe = tv.Recipe.load(CLOUDS, overrides=TINY)
    a, b = render_samples(recipe, [3], seed=5)[0], render_samples(recipe, [2, 3], seed=5)[1]
    H, W = 12, 16
    shapes = {"image": (3, 3, H, W), "depth": (3, 1, H, W), "alpha": (3, 1, H, W), "K": (3, 3, 3),
              "world_to_camera": (3, 4, 4), "flow": (3, 2, H, W), "flow_valid": (3, 1, H, W), "depth_median": (3, 1, H, W)}
    for key, shape in shapes.items():
        assert a[key].shape == shape and a[key].dtype == torch.float32, key
        assert torch.equal(a[key], b[key]), f"{key} depends on the batch"
    assert a["params"] == b["params"] and "dataset.camera_path.velocity" in a["params"]
    assert (a["flow"][-1] == 0).all() and (a["flow_valid"][-1] == 0).all() and a["flow_valid"][0].mean() > 0.2
    assert not torch.equal(a["world_to_camera"][0], a["world_to_camera"][1])  # the camera moved
    single = render_samples(tv.Recipe.load(CLOUDS, overrides={**TINY, "dataset.frames": 1}), [3], seed=5)[0]
    assert "flow" not in single and single["image"].shape == (3, H, W)
    for key in ("image", "depth", "alpha", "K", "world_to_camera", "depth_median"):
        assert torch.equal(single[key], a[key][0]), f"frame 0 differs from the single-frame sample in {key}"


def test_time_moves_the_clouds_and_a_still_sequence_repeats_its_frame():
    still = {**TINY, "dataset.camera_path": {}}
    moving = render_samples(tv.Recipe.load(CLOUDS, overrides=still), [3], seed=5)[0]
    assert torch.equal(moving["world_to_camera"][0], moving["world_to_camera"][2])
    assert (moving["image"][0] - moving["image"][1]).abs().max() > 0.02, "dt > 0: the wind moves the clouds"
    frozen = render_samples(tv.Recipe.load(CLOUDS, overrides={**still, "dataset.dt": 0.0}), [3], seed=5)[0]
    assert all(torch.equal(frozen[k][0], frozen[k][f]) for k in ("image", "depth", "alpha") for f in (1, 2))
    assert_close(frozen["flow"], torch.zeros_like(frozen["flow"]), atol=1e-4, what="flow of a still camera")


@pytest.mark.parametrize("key,value,match", [
    ("dataset.frames", 0, r"dataset\.frames"), ("dataset.frames", 2.5, r"dataset\.frames"),
    ("dataset.frames", 5000, r"dataset\.frames"), ("dataset.dt", -1.0, r"dataset\.dt"),
    ("dataset.dt", float("nan"), r"dataset\.dt"), ("dataset.camera_path.speed", 1.0, r"dataset\.camera_path\.speed"),
    ("dataset.camera_path.look_at", "ahead", r"dataset\.camera_path\.look_at"),
    ("dataset.camera_path.velocity", [1.0, 2.0], r"dataset\.camera_path\.velocity"),
    ("dataset.camera_path.velocity", {"uniform": [0, 1]}, r"dataset\.camera_path\.velocity"),
    ("dataset.camera_path.orbit", {"uniform": [[0, 0, 0], [1, 1, 1]]}, r"dataset\.camera_path\.orbit"),
    ("dataset.camera_path.orbit", {"uniformly": [0, 1]}, r"dataset\.camera_path\.orbit.*distribution"),
    ("dataset.views", 4, r"views"),
])
def test_bad_sequence_keys_are_refused_at_load(key, value, match):
    with pytest.raises(ValueError, match=match):
        tv.Recipe.load(CLOUDS, overrides={key: value})


def test_a_path_through_the_target_is_refused_naming_the_camera_path():
    data = _terrain_sequence(velocity=[0.0, -3.0, 6.0], look_at="fixed")  # the eye reaches the target at t = 1
    with pytest.raises(ValueError, match=r"dataset\.camera_path.*frame 1"):
        render_samples(tv.Recipe.load(data), [0])


@pytest.mark.parametrize("layout", ["folder", "webdataset"])
def test_generated_sequences_read_back(tmp_path, layout):
    overrides = {**TINY, "dataset.frames": 2}
    generate(CLOUDS, count=1, out=tmp_path / "ds", seed=5, overrides=overrides, layout=layout)
    live = tv.SceneDataset(CLOUDS, 1, seed=5, overrides=overrides)[0]
    meta = json.loads((tmp_path / "ds" / "meta.json").read_text())
    assert meta["frames"] == 2 and "flow" in meta["sequence"]
    if layout == "folder":
        back = tv.FolderDataset(tmp_path / "ds")[0]
        record = json.loads((tmp_path / "ds" / "manifest.jsonl").read_text())
        assert record["files"]["image"] == ["samples/000000.image.0.png", "samples/000000.image.1.png"]
        assert back.keys() == live.keys()
        for key in ("depth", "depth_median", "K", "world_to_camera", "flow", "flow_valid"):
            assert torch.equal(back[key], live[key]), key
        for key in ("image", "alpha"):
            assert back[key].shape == live[key].shape and (back[key] - live[key]).abs().max() <= 0.5 / 255 + 1e-6, key
        assert back["params"] == live["params"]
        return
    with tarfile.open(tmp_path / "ds" / "shards" / "shard-000000.tar") as tar:
        names = tar.getnames()
    assert {"000000.json", "000000.depth.1.npy", "000000.flow.npz", "000000.flow_valid.npz"} <= set(names)
    wds = pytest.importorskip("webdataset")
    s = next(iter(wds.WebDataset([str(tmp_path / "ds" / "shards" / "shard-000000.tar")], shardshuffle=False)))
    from torchvol.dataset.codec import decode_file

    assert torch.equal(decode_file("flow.npz", s["flow.npz"]), live["flow"])
    assert torch.equal(decode_file("depth.npy", s["depth.1.npy"]), live["depth"][1])
