"""What a surface pass (the voxels, the terrain) hands the render for one chunk of rays: below
both passes and the composite, so each of them names the same value."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

__all__ = ["SurfaceHit"]


@dataclass(frozen=True)
class SurfaceHit:
    """A surface pass's result per ray [R]: `hit` bool; `t` the world distance of the hit (inf
    where missed; the volumes march up to it); `color` [R, 3] what the ray sees behind any volume
    (the shaded surface where hit, else the background it was given); `aovs` AOV name (the AOV
    registry's) -> [R, C], the planned AOVs the pass outputs (0 where missed)."""

    hit: Tensor
    t: Tensor
    color: Tensor
    aovs: dict[str, Tensor]
