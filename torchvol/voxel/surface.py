"""The voxel surface pass of a render: a batch's voxel grids and the per-chunk pipeline
(traversal, variants, shading, AO, shadow rays, fog, glow) assembled from the passes of `passes/`,
which all trace through one `VoxelTracer` (tracer.py).

`VoxelSurface.run(o, d, s, background, section)` returns a `SurfaceHit`, per ray [n]: ``hit``,
``t`` (world distance of the first hit, inf for misses), ``color`` [n, 3] (what the ray sees behind
any volume: the shaded surface where hit, else `background`, with fog and glow applied) and the AOVs
the plan calls for (``normal`` [n, 3], ``uv`` [n, 2], ``material``, ``ao``, ``shadow``,
``roughness``, ``metallic``, ``water`` and ``water_floor_distance`` [n, 1]). With `voxels.water` a
ray that reaches the water plane first is a hit there: its colour mixes a reflected and a refracted
ray (`passes/water.py`).

GGX materials (`ggx.py`) shade the sun and, with `voxels.reflections`, add a mirror reflection
ray traced through the same DDA and shaded the same way (AO, shadows, GGX; not the rounded, glow
or fog variants), the sky where it misses, weighted by F · (1 − roughness)²: rough surfaces use the
mirror direction faded out, not a sampled lobe (an approximation). Default materials (roughness 1,
metallic 0) stay Lambert, bit for bit.
`voxels.gi` replaces the ambient with path-traced bounces (`passes/paths.py`) or, with `method =
"cone"`, with cones through a mip chain of the grids' opacity and reflected light (`passes/cones.py`).
Every per-scene value arrives as a (B, ...) tensor of the batch's `Stacked` voxels, or is handled
scene by scene (occupancy, texture atlas, the glow's SDF).
"""

from __future__ import annotations

from contextlib import nullcontext
from typing import Callable, Mapping, Sequence

import torch
from torch import Tensor

from ..geometry.surface_hit import SurfaceHit
from ..light.lights import LightSource
from ..ops.mathops import take_rows
from ..schema.batch import Stacked
from .dda import Hits
from .grid import VoxelGrid
from .passes.cones import ConeGI
from .passes.direct import DirectLight
from .passes.fog import FogGlow
from .passes.paths import PathGI
from .passes.rounded import RoundedVoxels
from .passes.secondary import SecondaryRays
from .passes.shading import Shading
from .passes.water import Water
from .tracer import VoxelTracer

__all__ = ["VoxelSurface"]

SURFACE_AOVS = ("normal", "uv", "material", "ao", "shadow", "roughness", "metallic", "water", "water_floor_distance")


class VoxelSurface:
    """One batch's voxel grids and shading parameters (`voxels`: the batch's `Stacked` voxels),
    lit by `lights`; `plan` the batch's `VoxelPass`; `aovs` the AOVs to output, name -> channels; `time` (B,) the
    scenes' times (water waves); `sky(directions [n, 3], s [n]) -> [n, 3]` what secondary rays that
    leave the grid see (None: black); `transmittance(use, p, s, direction, distance, times=None) -> [n]`
    `times` × what a shadow ray of LightPass `use` sees besides the voxels (the terrain beside them,
    where `use.terrain`), traced only where `times` > 0; `occluder_lanes(uses, s)` the same inside
    the shading's kernel (`volume.kernel_march.surface_lanes_of`; None: none)."""

    def __init__(self, voxels: Stacked, lights: Sequence[LightSource], plan, aovs: Mapping[str, int], *, dtype, device,
                 drjit: bool = False, time: Tensor | None = None, sky: Callable[[Tensor, Tensor], Tensor] | None = None,
                 transmittance: Callable[..., Tensor] | None = None, occluder_lanes: Callable | None = None):
        self.p, self.lights, self.plan = voxels, list(lights), plan
        self.grid = VoxelGrid.from_specs(voxels.models, dtype=dtype, device=device, with_distance=plan.traversal == "hybrid")
        self.aov_channels = {a: c for a, c in aovs.items() if a in SURFACE_AOVS}
        self.tracer = VoxelTracer(self.grid, plan.traversal, drjit)
        direct = DirectLight(voxels, plan, self.lights, self.tracer, transmittance)
        self.shading = Shading(voxels, plan, self.grid, direct, occluder_lanes)
        self.secondary = SecondaryRays(voxels, self.tracer, self.shading, sky)
        self.fog = FogGlow(voxels, plan, self.lights, self.tracer)
        self.rounded = RoundedVoxels(voxels, self.tracer)
        self.water = Water(voxels, time, self.secondary)
        self.paths = PathGI(voxels, plan, self.tracer, self.shading, direct, sky)
        self.cones = ConeGI(voxels, plan, self.grid, self.shading, direct, sky)

    @property
    def steps_total(self) -> int:
        """The DDA steps of every primary, secondary and GI ray traced so far (the `voxel_steps` stat)."""
        return self.tracer.steps_total

    def visibility(self, p: Tensor, s: Tensor, light: LightSource, steps: int) -> Tensor:
        """Visibility [n] (1 lit, 0 occluded) of points p [n, 3] of scenes s [n] towards `light`
        through the voxels (a shadow ray of at most `steps` cells)."""
        return self.tracer.visibility(p, s, light, steps)

    def run(self, o: Tensor, d: Tensor, s: Tensor, background: Tensor,
            section: Callable[[str], object] = lambda name: nullcontext(), keys: Tensor | None = None) -> SurfaceHit:
        """o, d [n, 3] world rays (d unit); s [n] scenes; background [n, 3]; keys [n, 3] long: each
        ray's (sub-pixel column, row, scene seed), the hash cells of its GI paths (needed with `voxels.gi`)."""
        gathered = self.fog.rays(o, s) if self.plan.glow or self.plan.fog else None
        walks = {} if gathered is None else {"visit": gathered.visit, "fog": gathered.walked, "glow": gathered.glowed}
        with section("voxels.dda"):
            hits = self.tracer.traverse(o, d, s, max_steps=self.p.max_steps, **walks)
        if gathered is not None:
            with section("voxels.fog") if self.plan.fog else nullcontext():
                gathered.finish()
        normal_override = None
        if self.plan.rounded:
            with section("voxels.rounded"):
                hits, normal_override = self.rounded(o, d, s, hits)
        self.tracer.count(hits.steps)
        color, aovs = self._shade(o, d, s, hits, normal_override, background, keys, section)
        if gathered is not None:
            color = gathered.apply(color)
        hit, t = hits.hit, torch.where(hits.hit, hits.t, torch.full_like(hits.t, torch.inf))
        if self.plan.water:
            hit, t, color = self.water(o, d, s, t, color, aovs, section)
        return SurfaceHit(hit=hit, t=t, color=color, aovs=aovs)

    def _shade(self, o: Tensor, d: Tensor, s: Tensor, hits: Hits, normal_override: Tensor | None, background: Tensor,
               keys: Tensor | None, section) -> tuple[Tensor, dict[str, Tensor]]:
        """The colour [n, 3] (`background` [n, 3] where missed) and the AOVs (name -> [n, C]) of the
        primary `hits` of rays o, d [n, 3] of scenes s [n]: shading, AO, GI, direct light, reflections."""
        n, t = o.shape[0], hits.t
        ids = hits.hit.nonzero().squeeze(1)
        color = background.clone()
        aovs = {k: o.new_zeros(n, c) for k, c in self.aov_channels.items()}
        if not ids.numel():
            return color, aovs
        sh = take_rows(s, ids)
        rows = [take_rows(x, ids) for x in (o, d, t, hits.cell, hits.axis, hits.material)]
        normal = None if normal_override is None else take_rows(normal_override, ids)
        indirect = None  # the GI's light in place of the ambient, from the hits' points
        if self.plan.cone:
            indirect = lambda point: self.cones(point, sh, take_rows(t, ids), section)  # noqa: E731
        elif self.plan.gi:
            def indirect(point):
                with section("voxels.gi"):
                    return self.paths(point, sh, take_rows(keys, ids), take_rows(t, ids))
        lit, point = self.shading.shade(*rows, sh, normal, section, indirect)
        color.index_copy_(0, ids, lit)  # (1.6× faster than color[ids] =)
        if self.plan.reflections:
            with section("voxels.reflections"):
                self.secondary.reflect(color, ids, point, take_rows(d, ids), sh, self.plan.reflections, section)
        for k in self.aov_channels:
            value = point.aov(k)
            if value is not None:  # the water's AOVs come from `Water`
                aovs[k].index_copy_(0, ids, value)
        return color, aovs
