"""A scene's surfaces as one pass: the voxels, the terrain, or both (`[voxels]` and `[terrain]`
in one scene), each primary ray taking the nearer of the two hits.

With both, the terrain traces and shades first and the voxels run with its colour as their
background (so the voxels' fog and glow lie over the terrain seen past them); per ray the hit with
the smaller t wins (ties: the voxels) with its colour, t, `depth` and AOVs. Where the terrain wins,
the voxel-only AOVs read as on a miss (0) but ``normal`` (the terrain's) and ``material`` (the
terrain's id, `terrain_id`: one past the voxel materials). The two surface classes are unchanged;
each one's shadow rays see the other through the plan's `LightPass` (`terrain`, `voxels`), the
voxels as an `Occluder` (`VoxelOccluder`) like the terrain.
"""

from __future__ import annotations

from contextlib import nullcontext
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from ..geometry.surface_hit import SurfaceHit
from ..ops import lanes
from ..schema.batch import Stacked
from ..terrain import TerrainSurface
from ..voxel.surface import VoxelSurface
from ..voxel.tracer import VoxelTracer
from ..voxel.walk import visible_walk, walk_inputs

__all__ = ["BothSurfaces", "SurfacesHit", "VoxelOccluder", "surface_pass", "terrain_id", "voxel_shadow_steps"]


def terrain_id(batch: Stacked) -> int:
    """The terrain's surface id (the ``material`` AOV where it is hit beside voxels, and the
    ``instance`` label's V + id): one past the voxel materials, so 1 without voxels."""
    return 1 + (0 if batch.voxels is None else len(batch.voxels.materials))


def voxel_shadow_steps(voxels: Stacked) -> int:
    """DDA cells of a shadow ray through the voxels cast by another pass (the terrain's, the
    volumes', the ``sun_visibility`` label's): `voxels.shadow.steps`, else `voxels.max_steps`."""
    return voxels.shadow.steps if voxels.shadow is not None else voxels.max_steps


class VoxelOccluder:
    """The voxels as an `Occluder` (`volume/context.py`): a shadow ray of at most `steps` cells
    through the grids of `tracer` (no hybrid skip), ending at `distance`."""

    def __init__(self, tracer: VoxelTracer, steps: int):
        self.tracer, self.steps = tracer, steps

    def visibility(self, p: Tensor, direction: Tensor, s: Tensor, distance: Tensor) -> Tensor:
        """1 where the ray from `p` [n, 3] along unit `direction` [n, 3] of scenes `s` [n] reaches
        `distance` [n] (inf: a sun) without meeting a voxel, else 0 -> [n]."""
        if p.shape[0] == 0:
            return p.new_zeros(0)
        t_max = None if bool(torch.isinf(distance).all()) else distance
        return (~self.tracer.traverse(p, direction, s, max_steps=self.steps, t_max=t_max, plain=True).hit).to(p.dtype)

    def visibility_lanes(self, s: Tensor, per_lane):
        """`visibility` inside a Dr.Jit kernel its caller traces, for lanes of scenes `s` [n]
        (`per_lane`: per scene -> lanes): visible(p, direction, distance) -> 1.0 or 0.0 (lanes; a
        distance of inf: a sun), the same plain walk (`walk.visible_walk`)."""
        r, g = walk_inputs(self.tracer.grid, s, per_lane, lanes.ints_of, kernel=True, max_steps=self.steps)
        return visible_walk(r, g, g.max_steps)


@dataclass(frozen=True)
class SurfacesHit(SurfaceHit):
    """The nearer of the two surfaces' hits per ray; `terrain` [n] bool: where the terrain won."""

    terrain: Tensor


def nearest(voxels: SurfaceHit, terrain: SurfaceHit, surface_id: float) -> SurfacesHit:
    """Per ray, the nearer of the voxels' and the terrain's hits (ties: the voxels); `voxels` ran
    with the terrain's colour as background. The voxels' AOVs where the terrain wins: its
    ``normal``, ``material`` = `surface_id`, the others 0 (as on a miss)."""
    won = terrain.hit & (terrain.t < voxels.t)
    over = (won & voxels.hit)[:, None]  # where the voxels missed, their colour already is the terrain's
    aovs = {}
    for key, value in voxels.aovs.items():
        if key in terrain.aovs:
            other = terrain.aovs[key]
        elif key == "material":
            other = torch.full_like(value, surface_id)
        else:
            other = torch.zeros_like(value)
        aovs[key] = torch.where(won[:, None], other, value)
    return SurfacesHit(hit=voxels.hit | terrain.hit, t=torch.where(won, terrain.t, voxels.t),
                       color=torch.where(over, terrain.color, voxels.color), aovs=aovs, terrain=won)


class BothSurfaces:
    """The voxel surface and the terrain of one batch as one surface pass (`nearest`); `surface_id`
    the terrain's material id among the voxels' (`terrain_id`)."""

    def __init__(self, voxels: VoxelSurface, terrain: TerrainSurface, surface_id: int):
        self.voxels, self.terrain, self.surface_id = voxels, terrain, float(surface_id)

    @property
    def steps_total(self) -> int:
        """The voxels' DDA steps so far (the `voxel_steps` stat)."""
        return self.voxels.steps_total

    def run(self, o: Tensor, d: Tensor, s: Tensor, background: Tensor,
            section: Callable[[str], object] = lambda name: nullcontext(), keys: Tensor | None = None) -> SurfacesHit:
        """o, d [n, 3] world rays (d unit); s [n] scenes; background [n, 3]; keys [n, 3] the voxels'
        GI hash cells (with `voxels.gi`) -> the nearer hit per ray."""
        ground = self.terrain.run(o, d, s, background, section)
        blocks = self.voxels.run(o, d, s, ground.color, section, keys=keys)
        return nearest(blocks, ground, self.surface_id)


def surface_pass(voxels: VoxelSurface | None, terrain: TerrainSurface | None, surface_id: int):
    """What the render runs as its surface pass: the one surface the batch has, both as one
    (`BothSurfaces`), or None."""
    if voxels is not None and terrain is not None:
        return BothSurfaces(voxels, terrain, surface_id)
    return voxels if voxels is not None else terrain
