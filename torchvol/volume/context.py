"""What a medium's passes read of the render they run in: a narrow, typed interface.

`renderer.executor.RenderContext` is the one implementation; the volume passes (strategies,
shadings, shadow rays, the Dr.Jit kernels) and the renderer's labels take it as a `VolumeContext`,
so they see exactly these members and nothing of the executor's.
"""

from __future__ import annotations

from contextlib import AbstractContextManager
from typing import Any, Protocol, Sequence

import torch
from torch import Tensor

from ..geometry.camera import Rays
from ..light.lights import LightSource
from .march import MarchSettings


class Timer(Protocol):
    """Where a pass's time is recorded (`renderer.stats.Timer`)."""

    def section(self, name: str) -> AbstractContextManager[None]:
        """A block timed as pass `name` (exclusive of the sections nested in it)."""


class Counts(Protocol):
    """The render's counters (`renderer.stats.Counts`)."""

    density_evals: int
    march_steps: int
    truncated_rays: int
    error_estimate: float


class Occluder(Protocol):
    """A surface that blocks shadow rays (the voxel surface, the terrain)."""

    def visibility(self, p: Tensor, direction: Tensor, s: Tensor, distance: Tensor) -> Tensor:
        """Transmittance [n] of rays from `p` [n, 3] along unit `direction` [n, 3] of scenes `s` [n]
        up to `distance` [n] (inf: a sun): 0 where the surface blocks them, else 1."""


class WalkedOccluder(Occluder, Protocol):
    """The voxels: an `Occluder` whose walk also runs inside a march's Dr.Jit kernel."""

    def visibility_lanes(self, s: Tensor, per_lane) -> Any:
        """`visibility` in lanes for rays of scenes `s` [n] (`per_lane`: per scene -> lanes):
        visible(p, direction, distance) -> 1.0 or 0.0."""


class VolumeContext(Protocol):
    """A render as the volume passes see it: its march settings, lights and volumes (each a
    `renderer.executor.VolumeState`: parameters, plan, field, bounds, phase, shading, caches),
    the surfaces shadow rays meet (`terrain`, `voxels`: where a `LightPass` names them), its timer
    and counters, its float type and device."""

    settings: MarchSettings
    lights: Sequence[LightSource]
    volumes: Sequence[Any]
    terrain: Occluder | None
    voxels: WalkedOccluder | None
    timer: Timer
    counts: Counts
    dtype: torch.dtype
    device: torch.device

    def dither(self, rays: Rays) -> Tensor | None:
        """The march's start offset per ray [R], or None (`march.dither = "none"`)."""

    def radiance_scale(self, scene_index: Tensor) -> Tensor:
        """What `march.tolerance` is relative to, per ray [R]."""

    def sun(self) -> Tensor | None:
        """(B, 3) towards the scene's sun, None: no sun."""


__all__ = ["Counts", "Occluder", "Timer", "VolumeContext"]
