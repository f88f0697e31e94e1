"""The direct light at voxel hits: each light's Lambert irradiance (the `diffuse` voxel material)
and, for GGX materials, its reflected radiance, each shadowed by a DDA ray towards the light
where the plan traces the light's shadows (`voxels.shadow`); with a terrain in the scene too, the
shadow ray also meets it (`LightPass.terrain`, through the render's `transmittance`)."""

from __future__ import annotations

from typing import Callable, Sequence

import torch
from torch import Tensor

from ...light.lights import LightSource
from ...schema.batch import Stacked, take
from ..ggx import ggx_reflect
from ..materials import VOXEL_MATERIALS
from ..tracer import VoxelTracer
from .point import ShadingPoint
from .rounded import cell_exit

__all__ = ["DirectLight"]


class DirectLight:
    """`lights` at the hits of the batch's voxels (`voxels`: its `Stacked` voxels; `plan` its
    `VoxelPass`), shadow rays traced by `tracer`; `transmittance(use, p, s, direction, distance) -> [n]`
    what a shadow ray of LightPass `use` sees besides the voxels (the volumes `use.occluders`, the
    terrain where `use.terrain`)."""

    def __init__(self, voxels: Stacked, plan, lights: Sequence[LightSource], tracer: VoxelTracer,
                 transmittance: Callable[..., Tensor] | None = None):
        self.p, self.plan, self.lights, self.tracer = voxels, plan, list(lights), tracer
        self.transmittance = transmittance
        self.material = VOXEL_MATERIALS["diffuse"]

    def __call__(self, point: ShadingPoint, s: Tensor, section, light: Tensor) -> tuple[Tensor, Tensor | int]:
        """`light` [n, 3] plus the lights' Lambert irradiance per unit albedo at the points of
        scenes s [n] (summed in this order: renders without GI are bitwise as before), and the
        lights' GGX reflected radiance [n, 3] (0 without GGX). The first shadowed light's
        visibility becomes the point's `shadow`."""
        p, specular = self.p, 0
        shadows = {use.light: use for use in self.plan.shadows}
        for l, source in enumerate(self.lights):
            toward = source.toward(point.x, s)
            vis = torch.ones_like(point.x[:, 0])
            if l in shadows:
                use = shadows[l]
                with section(use.name):
                    if p.rounded is None:
                        start = point.x + take(p.shadow.offset, s)[:, None] * point.face_normal
                    else:  # a rounded box lies inside its cell: its shadow ray leaves the cell first
                        leave = cell_exit(self.tracer.grid, point.x, toward.direction, s, point.cell)
                        start = point.x + (leave + take(p.shadow.offset, s))[:, None] * toward.direction
                    at_start = None if source.directional else source.toward(start, s)
                    vis = self.tracer.visibility(start, s, source, p.shadow.steps, at_start)
                if use.terrain or use.occluders:  # the media and the terrain beside the voxels (their own passes)
                    at_start = source.toward(start, s) if at_start is None else at_start
                    vis = self.transmittance(use, start, s, at_start.direction, at_start.distance, vis)
                if point.shadow is None:
                    point.shadow = vis[:, None]
            light = light + self.material.fn(point.normal, toward.direction, toward.irradiance, vis)
            if self.plan.ggx:
                specular = specular + (ggx_reflect(point.normal, point.view, toward.direction, point.albedo,
                                                   point.roughness[:, 0], point.metallic[:, 0], kernel=self.tracer.drjit)
                                       * toward.irradiance * vis[:, None])
        return light, specular
