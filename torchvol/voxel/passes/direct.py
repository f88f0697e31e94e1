"""The direct light at voxel hits on torch columns (`look.direct_lanes`, the fused kernel's
source too): each light's Lambert irradiance (the `diffuse` voxel material) and, for GGX
materials, its reflected radiance, each shadowed by a DDA ray towards the light where the plan
traces the light's shadows (`voxels.shadow`), traced by the `VoxelTracer`; with a terrain or
volumes in the scene too, the shadow ray also meets them (`LightPass.terrain`, `.occluders`,
through the render's `transmittance`)."""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Callable, Sequence

import torch
from torch import Tensor

from ...light.lights import LightSource, Toward
from ...ops import lanes
from ...schema.batch import Stacked, take
from ..ggx import ggx_reflect
from ..tracer import VoxelTracer
from .look import direct_lanes, look_inputs, look_tables
from .point import ShadingPoint

__all__ = ["DirectLight", "point_lanes_view"]


def point_lanes_view(point: ShadingPoint) -> SimpleNamespace:
    """A `ShadingPoint`'s fields as the look's lanes functions read them (torch columns)."""
    col = lambda x: None if x is None else lanes.columns(x)  # noqa: E731
    one = lambda x: None if x is None else x[:, 0]  # noqa: E731
    return SimpleNamespace(x=col(point.x), cell=col(point.cell), face_normal=col(point.face_normal),
                           normal=col(point.normal), view=col(point.view), albedo=col(point.albedo),
                           roughness=one(point.roughness), metallic=one(point.metallic), emission=col(point.emission))


class DirectLight:
    """`lights` at the hits of the batch's voxels (`voxels`: its `Stacked` voxels; `plan` its
    `VoxelPass`), shadow rays traced by `tracer`; `transmittance(use, p, s, direction, distance) -> [n]`
    what a shadow ray of LightPass `use` sees besides the voxels (the volumes `use.occluders`, the
    terrain where `use.terrain`)."""

    def __init__(self, voxels: Stacked, plan, lights: Sequence[LightSource], tracer: VoxelTracer,
                 transmittance: Callable[..., Tensor] | None = None):
        self.p, self.plan, self.lights, self.tracer = voxels, plan, list(lights), tracer
        self.transmittance = transmittance
        self.tables = look_tables(voxels, plan)  # the materials and atlases, once a render

    def inputs(self, s: Tensor, like: Tensor, *, surface: bool = False) -> SimpleNamespace:
        """`look.look_inputs` on torch columns for hits of scenes s [n] (`like`'s dtype): the
        lights' (`surface`: the point's instead); GGX's reflectance one Dr.Jit kernel where the
        tracer's walks are (its sqrt correctly rounded, torch's float32 one not: the fused
        kernel's bits)."""
        q = look_inputs(self.p, self.plan, self.tables, self.tracer.grid, self.lights, s, lambda v: lanes.columns(take(v, s)),
                        lambda x: x.to(torch.int32), lambda x: x.to(like.dtype), kernel=False, walks=False,
                        surface=surface, light=not surface)
        if self.tracer.drjit and not surface:
            def reflect(*vectors_and_numbers):
                *vectors, rough, metal = vectors_and_numbers
                stack = lambda v: torch.stack(v, dim=1)  # noqa: E731
                return lanes.columns(ggx_reflect(*(stack(v) for v in vectors), rough, metal, kernel=True))

            q.reflect = reflect
        return q

    def shadow_rays(self, s: Tensor, section):
        """`direct_lanes`' visible(l, start, direction, distance) on torch columns of scenes s [n]:
        the tracer's shadow walk towards light l (each its pass, timed by `section`), then what the
        ray meets beside the voxels (the render's `transmittance`, where it is > 0)."""
        shadows = {use.light: use for use in self.plan.shadows}

        def visible(l: int, start: list, direction: list, distance) -> Tensor:
            use, source = shadows[l], self.lights[l]
            start, direction = torch.stack(start, dim=1), torch.stack(direction, dim=1)
            distance = torch.full_like(start[:, 0], math.inf) if isinstance(distance, float) else distance
            with section(use.name):
                vis = self.tracer.visibility(start, s, source, self.p.shadow.steps, Toward(direction, None, distance))
            if use.terrain or use.occluders:  # the media and the terrain beside the voxels (their own passes)
                vis = self.transmittance(use, start, s, direction, distance, vis)
            return vis

        return visible

    def __call__(self, point: ShadingPoint, s: Tensor, section, light: Tensor) -> tuple[Tensor, Tensor | int]:
        """`light` [n, 3] plus the lights' Lambert irradiance per unit albedo at the points of
        scenes s [n] (summed in this order: renders without GI are bitwise as before), and the
        lights' GGX reflected radiance [n, 3] (0 without GGX). The first shadowed light's
        visibility becomes the point's `shadow`."""
        shadows = {use.light: use for use in self.plan.shadows}
        q = self.inputs(s, point.x)
        light, specular, first = direct_lanes(q, point_lanes_view(point), lanes.columns(light), self.shadow_rays(s, section),
                                              shadows)
        if point.shadow is None and first is not None:
            point.shadow = first[:, None]
        return torch.stack(light, dim=1), (0 if specular is None else torch.stack(specular, dim=1))
