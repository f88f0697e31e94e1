"""Secondary rays through the voxels (off the water, mirror reflections), traced through the same
DDA and shaded as primary hits are (AO, shadows, GGX; not the rounded, glow or fog variants), the
sky where they leave the grid; and the mirror reflections of GGX materials (`voxels.reflections`),
weighted by F · (1 − roughness)²: rough surfaces use the mirror direction faded out, not a sampled
lobe (an approximation)."""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from ...ops.mathops import take_rows
from ...schema.batch import Stacked
from ..ggx import f0_of, f_schlick
from ..tracer import VoxelTracer
from .point import ShadingPoint
from .shading import Shading

__all__ = ["REFLECTION_OFFSET", "SecondaryRays"]

REFLECTION_OFFSET = 1e-3  # the seed's hitPos + normal · 0.001, in voxels


class SecondaryRays:
    """Secondary rays of the batch's voxels (`voxels`: its `Stacked` voxels) traced by `tracer`,
    their hits shaded by `shading`; `sky(directions [n, 3], s [n]) -> [n, 3]` what rays that
    leave the grid see (None: black)."""

    def __init__(self, voxels: Stacked, tracer: VoxelTracer, shading: Shading,
                 sky: Callable[[Tensor, Tensor], Tensor] | None):
        self.p, self.tracer, self.shading, self.sky = voxels, tracer, shading, sky

    def reflect(self, color: Tensor, ids: Tensor, point: ShadingPoint, d: Tensor, s: Tensor, bounces: int,
                section) -> None:
        """Adds into color[ids] [n, 3] the mirror reflection of the hits `point` seen along d [n, 3]
        (scenes s [n]), weighted by Fresnel · (1 − roughness)²; only where that weight is not 0."""
        rough = point.roughness[:, 0]
        f = f_schlick(f0_of(point.albedo, point.metallic[:, 0]), (point.normal * -d).sum(-1, keepdim=True))
        weight = f * ((1.0 - rough) * (1.0 - rough))[:, None]
        live = (weight > 0).any(dim=1).nonzero().squeeze(1)
        if not live.numel():
            return
        n, dl, sl = (take_rows(x, live) for x in (point.normal, d, s))  # (index_select: 3× faster than x[live])
        r = dl - 2.0 * (dl * n).sum(-1, keepdim=True) * n
        off = (REFLECTION_OFFSET * take_rows(self.tracer.grid.voxel_size, sl))[:, None]
        start = take_rows(point.x, live) + off * take_rows(point.face_normal, live)
        seen = self.trace_shade(start, r, sl, section, max_steps=self.p.reflections.steps, bounces=bounces)[0]
        color.index_add_(0, take_rows(ids, live), take_rows(weight, live) * seen)  # (unique rows: color[...] += bitwise, 3× faster)

    def trace_shade(self, o: Tensor, d: Tensor, s: Tensor, section, *, max_steps: int,
                    bounces: int = 0) -> tuple[Tensor, Tensor]:
        """A secondary ray (off the water, or a reflection) o, d [n, 3] (d unit) of scenes s [n]
        through the voxels, its hit lit like a primary one (AO, shadows, materials; its own
        reflection while `bounces` > 1 remain), the sky where it leaves -> (colour [n, 3], hit
        distance [n], inf: none)."""
        h = self.tracer.traverse(o, d, s, max_steps=max_steps, plain=True)
        self.tracer.count(h.steps)
        color = o.new_zeros(o.shape[0], 3) if self.sky is None else self.sky(d, s).clone()  # a sky may be expanded
        ids = h.hit.nonzero().squeeze(1)
        if ids.numel():
            sh, di = take_rows(s, ids), take_rows(d, ids)
            hit = [take_rows(x, ids) for x in (o, h.t, h.cell, h.axis, h.material)]
            lit, point = self.shading.shade(hit[0], di, *hit[1:], sh, None, section)
            color.index_copy_(0, ids, lit)
            if bounces > 1:
                self.reflect(color, ids, point, di, sh, bounces - 1, section)
        return color, torch.where(h.hit, h.t, torch.full_like(h.t, torch.inf))
