"""A sequence recipe's `[dataset]` keys (`frames`, `dt`, `camera_path`; `sequence.py` shows them)
validated into the SequenceSpec a Recipe holds (`Recipe.sequence`). Rendering the frames and their
flow is `sequence.py`'s, which builds on recipes: this module imports neither.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, Mapping

from ..schema.validate import fail, finite, is_integer, known_keys
from .distributions import DIST_KINDS, Dist, parse_dist

__all__ = ["SEQUENCE_KEYS", "SequenceSpec", "parse_sequence"]

SEQUENCE_KEYS = ("frames", "dt", "camera_path")
PATH_KEYS = ("velocity", "orbit", "look_at")
MAX_FRAMES = 1000
DEFAULT_DT = 1.0 / 24.0


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
