"""What a render records while it runs: wall time per pass, density evaluations, march steps.
`stats["passes"]` and `stats["time_s"]` come from here: the passes that ran, in the order they
first ran, each with its own exclusive time."""

from __future__ import annotations

import time
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from typing import Iterator

from torch import Tensor

from ..fields import Field
from ..fields.base import DENSITY_MAX


class Timer:
    """Exclusive wall time per pass: a nested section pauses the one around it. `seconds` keeps
    the order in which passes first ran."""

    def __init__(self):
        self.seconds: dict[str, float] = {}
        self._stack: list[list] = []

    @contextmanager
    def section(self, name: str) -> Iterator[None]:
        """Times the `with` block as pass `name`, pausing the section around it."""
        now = time.perf_counter()
        if self._stack:
            outer = self._stack[-1]
            self.seconds[outer[0]] = self.seconds.get(outer[0], 0.0) + now - outer[1]
        self.seconds.setdefault(name, 0.0)
        self._stack.append([name, now])
        try:
            yield
        finally:
            end = time.perf_counter()
            self.seconds[name] += end - self._stack.pop()[1]
            if self._stack:
                self._stack[-1][1] = end


@dataclass
class Counts:
    density_evals: int = 0
    march_steps: int = 0
    truncated_rays: int = 0
    voxel_steps: int = 0
    error_estimate: float = 0.0


# the points each counted field evaluates while `recording_points` asks for them (None: nobody asks)
_RECORDING: ContextVar[dict | None] = ContextVar("recording_points", default=None)


@contextmanager
def recording_points() -> Iterator[dict]:
    """Inside the block every `CountedField` keeps a copy of what it evaluates: yields {field:
    [(points [m, 3], scene_index [m], lod [m] or None), ...]} in the order evaluated. For the
    bench's floor on a render's own points (`measure.bench_speed`)."""
    record: dict = {}
    token = _RECORDING.set(record)
    try:
        yield record
    finally:
        _RECORDING.reset(token)


class CountedField:
    """A field that counts the points it evaluates: the render's `stats["density_evals"]`, and its
    own `evals` (`stats["density_evals_by_volume"]`); every density it returns is capped at
    `fields.base.DENSITY_MAX` (a huge constant, grid value or fbm amplitude would otherwise overflow
    σ_t · density to inf in float32, and the march's inf × 0 to NaN)."""

    def __init__(self, inner: Field, counts: Counts):
        self.inner, self.counts, self.evals = inner, counts, 0
        self.feature_size = inner.feature_size

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        self._count(points, scene_index, lod)
        return self.inner(points, scene_index, lod).clamp_max(DENSITY_MAX)

    def signed(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        """The inner field's signed density [n] at `points` [n, 3] of scenes `scene_index` [n]
        (`lod` [n] or None), its evaluations counted, capped at DENSITY_MAX as the density is."""
        self._count(points, scene_index, lod)
        return self.inner.signed(points, scene_index, lod).clamp_max(DENSITY_MAX)

    def _count(self, points: Tensor, scene_index: Tensor, lod: Tensor | None) -> None:
        self.counts.density_evals += points.shape[0]
        self.evals += points.shape[0]
        record = _RECORDING.get()
        if record is not None:
            record.setdefault(self, []).append((points.detach().clone(), scene_index.clone(),
                                                None if lod is None else lod.clone()))
