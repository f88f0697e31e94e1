"""Sequences: F frames of one drawn scene, time advancing and the camera moving, with optical flow.

A recipe's `[dataset]` table asks for them (validated by `sequence_spec.py`):

    [dataset]
    frames = 8                      # F >= 2 makes a sample a sequence (1, the default: single frames)
    dt = 0.5                        # seconds of scene `time` between frames (default 1/24)
    camera_path = { velocity = { uniform = [[-0.3, 0, -0.3], [0.3, 0, 0.3]] }, orbit = 4.0, look_at = "moving" }

Frame f (t = f·dt) is the sample's scene with `time + t` and the camera moved along its path:

    c_f    = target + velocity·t                                  (the orbit centre)
    eye_f  = eye + velocity·t + (Rot_y(orbit·t) − I)(eye − target)
    target_f = c_f (look_at = "moving", the default) or target ("fixed")

`velocity` (world units per second) translates the eye; `orbit` (degrees per second) adds to the
eye's azimuth about the vertical axis through the orbit centre (azimuth from +z towards +x, as the
recipe's `orbit` distribution). Each may be a number/vector or a distribution, drawn once per sample
like any recipe key (its key path `dataset.camera_path.velocity` in the sample's `params`). Frame 0
is the single-frame sample exactly (`frames = 1` gives it). Every frame renders with the sample's
render seed (dither and jitter fixed on the screen, so a still scene gives equal frames), and the F
frames of a batch of samples render as one batch.

A sample gains a leading F axis: image (F,3,H,W), depth/alpha (F,1,H,W), AOVs (F,C,H,W), K (F,3,3),
world_to_camera (F,4,4); and `flow` (F,2,H,W) float32 pixels, `flow_valid` (F,1,H,W) float32 0/1:
flow[f] is the forward flow from frame f to f+1 of the static geometry at frame f's depth
(`flow.flow_from_depth`); flow[F−1] is 0 with flow_valid 0 (no next frame).
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import torch

from ..scene.model import Scene
from ..schema.validate import SceneError, fail
from .codec import encode_sample, npz_bytes
from .recipe import Recipe

__all__ = ["camera_at", "frame_scenes", "sequence_scenes", "add_flow", "encode_item"]

# The meta.json conventions of a sequence dataset.
CONVENTIONS = {
    "frames": "image, depth, alpha and AOVs stored one file per frame: {index}.{name}.{frame}.{ext}; "
              "K (F,3,3) and world_to_camera (F,4,4) in the record",
    "flow": "flow.npz (F, 2, H, W) float32 pixels (dx, dy): frame f's depth point projected into frame f+1 minus "
            "its pixel centre, from planar depth and the two poses (static geometry; wind drift not followed); "
            "0 where flow_valid is 0; flow[F-1] = 0",
    "flow_valid": "flow_valid.npz (F, 1, H, W) uint8 0/1: depth > 0 and the point in front of the next camera",
}


def camera_at(eye: Sequence[float], target: Sequence[float], velocity: Sequence[float], orbit: float,
              t: float, look_at: str) -> tuple[list[float], list[float]]:
    """The eye and target at time t along the path (float64; exactly eye, target at t = 0)."""
    theta = math.radians(orbit * t)
    c, s = math.cos(theta), math.sin(theta)
    r = [e - g for e, g in zip(eye, target)]
    turned = [r[0] * c + r[2] * s - r[0], 0.0, -r[0] * s + r[2] * c - r[2]]  # (Rot_y(θ) − I) r
    new_eye = [e + v * t + d for e, v, d in zip(eye, velocity, turned)]
    new_target = [g + v * t for g, v in zip(target, velocity)] if look_at == "moving" else list(target)
    return new_eye, new_target


def frame_scenes(recipe: Recipe, scene: Scene, params: Mapping[str, Any], path: Mapping[str, Any]) -> list[Scene]:
    """The F scenes of one sample: its drawn values with `time` and the camera set per frame."""
    spec = recipe.sequence
    if scene.camera.matrix is not None and (any(path["dataset.camera_path.velocity"]) or path["dataset.camera_path.orbit"]):
        fail("dataset.camera_path", recipe.source.get("dataset", {}).get("camera_path"),
             "moves the camera's eye and target; a camera given by `camera.matrix` cannot move")
    out = []
    for f in range(spec.frames):
        t = f * spec.dt
        eye, target = camera_at(scene.camera.eye, scene.camera.target, path["dataset.camera_path.velocity"],
                                path["dataset.camera_path.orbit"], t, spec.look_at)
        try:
            out.append(recipe._scene({**params, "time": scene.time + t, "camera.eye": eye, "camera.target": target}))
        except SceneError as err:
            fail("dataset.camera_path", dict(path), f"frame {f} (t = {t:g} s) gives an invalid scene: {err}")
    return out


def sequence_scenes(recipe: Recipe, indices: Sequence[int], *, seed: int) -> tuple[list[list[Scene]], list[dict]]:
    """The F frame scenes of each sample `indices` and each sample's `params` (its drawn values and
    its camera path's)."""
    scenes, drawn = [], []
    for i in indices:
        scene, params = recipe.sample_with_params(int(i), seed)
        path = recipe.sequence.draw(int(i), seed)
        drawn.append({**params, **path})
        scenes.append(frame_scenes(recipe, scene, params, path))
    return scenes, drawn


def add_flow(item: dict) -> None:
    """Adds a stacked sequence sample's `flow` (F, 2, H, W) and `flow_valid` (F, 1, H, W): frame f to
    f + 1 from its depth and the two poses; the last frame's is 0 and invalid."""
    # kornia's import (0.13 s) only where a recipe has frames
    from .flow import flow_from_depth

    flow, valid = flow_from_depth(item["depth"][:-1], item["K"][:-1], item["world_to_camera"][:-1],
                                  item["world_to_camera"][1:])
    last = torch.zeros_like(flow[:1])
    item["flow"] = torch.cat([flow, last]).contiguous()
    item["flow_valid"] = torch.cat([valid.float(), last[:, :1]]).contiguous()


def encode_item(item: Mapping, aovs: Sequence[str]) -> dict[str, bytes]:
    """A sample's files (`encode_sample`: per frame as per view, image.{f}.png, ...), and a
    sequence's flow.npz (F,2,H,W) float32 and flow_valid.npz (F,1,H,W) uint8."""
    files = encode_sample(item, aovs)
    if "flow" in item:
        files["flow.npz"] = npz_bytes("flow", item["flow"].numpy())
        files["flow_valid.npz"] = npz_bytes("flow_valid", item["flow_valid"].numpy())
    return files
