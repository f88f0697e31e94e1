"""Sequences: F frames of one drawn scene, time advancing and the camera moving, with optical flow.

A recipe's `[dataset]` table asks for them:

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
from dataclasses import dataclass
from typing import Any, Literal, Mapping, Sequence

import torch

from .datasets import _npz, encode_sample
from .flow import flow_from_depth
from .recipe import DIST_KINDS, Dist, Recipe, parse_dist
from ..scene.model import Scene
from ..schema.validate import SceneError, fail, finite, is_integer, known_keys

__all__ = ["SEQUENCE_KEYS", "SequenceSpec", "parse_sequence", "frame_scenes", "sequence_scenes",
           "add_flow", "encode_item"]

SEQUENCE_KEYS = ("frames", "dt", "camera_path")
PATH_KEYS = ("velocity", "orbit", "look_at")
MAX_FRAMES = 1000
DEFAULT_DT = 1.0 / 24.0

# The meta.json conventions of a sequence dataset.
CONVENTIONS = {
    "frames": "image, depth, alpha and AOVs stored one file per frame: {index}.{name}.{frame}.{ext}; "
              "K (F,3,3) and world_to_camera (F,4,4) in the record",
    "flow": "flow.npz (F, 2, H, W) float32 pixels (dx, dy): frame f's depth point projected into frame f+1 minus "
            "its pixel centre, from planar depth and the two poses (static geometry; wind drift not followed); "
            "0 where flow_valid is 0; flow[F-1] = 0",
    "flow_valid": "flow_valid.npz (F, 1, H, W) uint8 0/1: depth > 0 and the point in front of the next camera",
}


@dataclass(frozen=True)
class SequenceSpec:
    """Validated `[dataset]` sequence keys. `velocity`/`orbit`: a fixed value or a Dist."""

    frames: int
    dt: float
    velocity: Any = (0.0, 0.0, 0.0)
    orbit: Any = 0.0
    look_at: Literal["moving", "fixed"] = "moving"

    def draw(self, index: int, seed: int) -> dict[str, Any]:
        """The sample's camera path: {key path: value}, drawn like a recipe key (seed, index, path)."""
        out = {}
        for name in ("velocity", "orbit"):
            value = getattr(self, name)
            path = f"dataset.camera_path.{name}"
            if isinstance(value, Dist):  # parsed at `path`: drawn like a recipe key
                value = value.draw(seed, index)
            out[path] = list(value) if name == "velocity" else value
        return out


def _path_value(path: str, raw: Any, check) -> Any:
    """A fixed value (checked) or a distribution whose corners pass the same check."""
    if isinstance(raw, Mapping):
        if len(raw) != 1 or next(iter(raw)) not in DIST_KINDS:
            fail(path, raw, "expected a value or a distribution table, one of: " + ", ".join(DIST_KINDS))
        dist = parse_dist(path, raw)
        for corner in dist.corners():
            check(path, corner)
        return dist
    return check(path, raw)


def _vec3(path: str, value: Any) -> tuple[float, float, float]:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        fail(path, value, "expected [x, y, z] world units per second (or a distribution of them)")
    return tuple(finite(f"{path}[{i}]", x) for i, x in enumerate(value))


def _number(path: str, value: Any) -> float:
    if isinstance(value, (list, tuple)):
        fail(path, value, "expected a number of degrees per second (or a distribution of them)")
    return finite(path, value)


def parse_sequence(meta: Mapping) -> SequenceSpec | None:
    """The sequence a recipe's `[dataset]` table asks for; None for single frames (frames = 1)."""
    if not any(key in meta for key in SEQUENCE_KEYS):
        return None
    frames = meta.get("frames", 1)
    if not is_integer(frames) or not 1 <= frames <= MAX_FRAMES:
        fail("dataset.frames", frames, f"expected an integer from 1 to {MAX_FRAMES}")
    dt = finite("dataset.dt", meta.get("dt", DEFAULT_DT))
    if dt < 0:
        fail("dataset.dt", dt, "expected seconds >= 0")
    views = meta.get("views", 1)
    if frames > 1 and views != 1:
        fail("dataset.frames", frames, f"sequences of several views are not supported (dataset.views = {views!r}); "
             "use frames or views")
    path = meta.get("camera_path", {})
    if not isinstance(path, Mapping):
        fail("dataset.camera_path", path, "expected a table { velocity = [x, y, z], orbit = deg/s, look_at = 'moving' }")
    known_keys("dataset.camera_path", path, PATH_KEYS)
    look_at = path.get("look_at", "moving")
    if look_at not in ("moving", "fixed"):
        fail("dataset.camera_path.look_at", look_at, "expected 'moving' (the target moves with the eye) or 'fixed'")
    spec = SequenceSpec(
        frames=int(frames), dt=dt,
        velocity=_path_value("dataset.camera_path.velocity", path.get("velocity", [0.0, 0.0, 0.0]), _vec3),
        orbit=_path_value("dataset.camera_path.orbit", path.get("orbit", 0.0), _number),
        look_at=look_at)
    return spec if spec.frames > 1 else None


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
        files["flow.npz"] = _npz("flow", item["flow"].numpy())
        files["flow_valid.npz"] = _npz("flow_valid", item["flow_valid"].numpy())
    return files
