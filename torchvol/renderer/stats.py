"""What a render records while it runs: wall time per pass, density evaluations, march steps.
`stats["passes"]` and `stats["time_s"]` come from here: the passes that ran, in the order they
first ran, each with its own exclusive time."""

from __future__ import annotations

import time
from contextlib import contextmanager
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


class CountedField:
    """A field that counts the points it evaluates: the render's `stats["density_evals"]`, and its
    own `evals` (`stats["density_evals_by_volume"]`); every density it returns is capped at
    `fields.base.DENSITY_MAX` (a huge constant, grid value or fbm amplitude would otherwise overflow
    σ_t · density to inf in float32, and the march's inf × 0 to NaN)."""

    def __init__(self, inner: Field, counts: Counts):
        self.inner, self.counts, self.evals = inner, counts, 0
        self.feature_size = inner.feature_size

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        self.counts.density_evals += points.shape[0]
        self.evals += points.shape[0]
        return self.inner(points, scene_index, lod).clamp_max(DENSITY_MAX)

    def signed(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        """The inner field's signed density [n] at `points` [n, 3] of scenes `scene_index` [n]
        (`lod` [n] or None), its evaluations counted, capped at DENSITY_MAX as the density is."""
        self.counts.density_evals += points.shape[0]
        self.evals += points.shape[0]
        return self.inner.signed(points, scene_index, lod).clamp_max(DENSITY_MAX)
