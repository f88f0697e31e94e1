"""`voxels.gi` with `method = "cone"`: cones through a mip chain of the grids' opacity and
reflected light (built once per render, by the first chunk that needs it) replace the ambient;
with `gi.ao` their visibility multiplies the albedo. The cone maths is `cone.py`'s."""

from __future__ import annotations

from contextlib import nullcontext
from typing import Callable

import torch
from torch import Tensor

from ...schema.batch import Stacked, take
from ..cone import (
    OFFSET,
    build_mips,
    cone_directions,
    default_aperture,
    face_cells,
    mip_table,
    trace_cones,
)
from ..grid import VoxelGrid
from ..shade_kernel import cones_kernel, mips_lanes
from .direct import DirectLight
from .point import ShadingPoint
from .shading import Shading

__all__ = ["ConeGI"]


class ConeGI:
    """The batch's cone-traced GI (`voxels`: its `Stacked` voxels; `plan` its `VoxelPass`) through
    `grid`'s mips, whose light `shading` and `direct` compute; `sky(directions [n, 3], s [n]) ->
    [n, 3]` what cones that leave the grid see (None: black); `mips` the chain once built."""

    def __init__(self, voxels: Stacked, plan, grid: VoxelGrid, shading: Shading, direct: DirectLight,
                 sky: Callable[[Tensor, Tensor], Tensor] | None):
        self.p, self.plan, self.grid, self.shading, self.direct, self.sky = voxels, plan, grid, shading, direct, sky
        self.mips = None
        self.drjit = direct.tracer.drjit  # the cones as one Dr.Jit kernel where the walks are

    def __call__(self, point: ShadingPoint, s: Tensor, distance: Tensor, section) -> Tensor:
        """The cones' incoming radiance [n, 3] at the hits `point` of scenes s [n], seen from the
        camera at `distance` [n] (world units); with `gi.ao` their visibility multiplies the
        point's albedo (and its `ao`)."""
        if self.mips is None:
            with section("voxels.gi.mips"):
                self.mips = self._mips()
                if self.drjit:
                    self.mips_lanes = mips_lanes(*mip_table(self.mips))
        with section("voxels.gi.cones"):
            return self._cones(point, s, distance)

    def _cones(self, point: ShadingPoint, s: Tensor, distance: Tensor) -> Tensor:
        """`__call__` once the mips are built."""
        gi, g = self.p.gi, self.grid
        n, dt = s.shape[0], point.x.dtype
        cones = gi.cones
        half = (torch.full((len(self.p),), default_aperture(cones), dtype=dt, device=s.device)
                if gi.aperture is None else gi.aperture)
        half = take(half, s)
        groups = [(torch.arange(n, device=s.device), cones)]
        if gi.lod is not None:
            near, far = take(gi.lod.near, s), take(gi.lod.far, s)
            w = ((distance - near) / (far - near)).clamp(0.0, 1.0)
            half = half + w * (take(gi.lod.aperture, s) - half)
            beyond = distance >= far
            groups = [(h, k) for h, k in (((~beyond).nonzero().squeeze(1), cones),
                                          (beyond.nonzero().squeeze(1), gi.lod.cones)) if h.numel()]
        ratio = 2.0 * torch.tan(torch.deg2rad(half))
        owner = torch.cat([h.repeat_interleave(k) for h, k in groups])
        weight = torch.cat([torch.full((h.numel() * k,), 1.0 / k, dtype=dt, device=s.device) for h, k in groups])
        d = torch.cat([cone_directions(point.face_normal[h], k).reshape(-1, 3) for h, k in groups])
        so = s[owner]
        origin = g.to_grid(point.x[owner], so) - g.lo[so].to(dt) + OFFSET * point.face_normal[owner]
        max_t = take(gi.max_distance, so) / g.voxel_size[so]
        if self.drjit:
            color, occ = cones_kernel(self.mips_lanes, origin, d, so, ratio[owner], steps=gi.steps, max_t=max_t)
        else:
            color, occ = trace_cones(self.mips, origin, d, so, ratio[owner], steps=gi.steps, max_t=max_t)
        if self.sky is not None:
            color = color + (1.0 - occ)[:, None] * self.sky(d, so)
        indirect = torch.zeros_like(point.x).index_add_(0, owner, weight[:, None] * color)
        if gi.ao:
            ao = torch.zeros_like(distance).index_add_(0, owner, weight * (1.0 - occ))[:, None]
            point.albedo = point.albedo * ao
            point.ao = ao if point.ao is None else point.ao * ao
        return indirect

    def _mips(self) -> list[Tensor]:
        """The mip chain (`cone.build_mips`) of the batch's grids: each cell's radiance the mean over
        its exposed faces of what a path-traced bounce sees there (albedo · direct light + emission,
        shaded by `Shading.point` and `DirectLight` at the face centre)."""
        g = self.grid
        occupied = g.materials > 0
        B, Z, Y, X = occupied.shape
        dt = g.origin.dtype
        faces = [(b, axis, sign, idx) for b in range(B) for axis, sign, idx in face_cells(occupied[b]) if idx.numel()]
        radiance = g.origin.new_zeros(B * Z * Y * X, 3)
        count = g.origin.new_zeros(B * Z * Y * X)
        if faces:
            idx = torch.cat([f[3] for f in faces])
            s = torch.cat([torch.full((f[3].shape[0],), f[0], dtype=torch.long, device=idx.device) for f in faces])
            axis = torch.cat([torch.full((f[3].shape[0],), f[1], dtype=torch.long, device=idx.device) for f in faces])
            outward = g.origin.new_zeros(idx.shape[0], 3)
            outward[torch.arange(idx.shape[0]), axis] = torch.cat([torch.full((f[3].shape[0],), float(f[2]), dtype=dt)
                                                                   for f in faces])
            cell = idx + g.lo[s]
            flat = ((s * Z + idx[:, 2]) * Y + idx[:, 1]) * X + idx[:, 0]
            # a ray from one voxel out, straight onto the face's centre
            x = g.to_world(cell.to(dt) + 0.5 + 0.5 * outward, s)
            size = g.voxel_size[s]
            hit = self.shading.point(x + size[:, None] * outward, -outward, size, cell, axis,
                                     g.materials.reshape(-1)[flat].long(), s, None)
            incoming, _ = self.direct(hit, s, lambda name: nullcontext(), torch.zeros_like(x))
            own = hit.albedo * incoming + (hit.emission if self.plan.emission else 0.0)
            radiance.index_add_(0, flat, own)
            count.index_add_(0, flat, torch.ones_like(flat, dtype=dt))
        radiance = (radiance / count.clamp_min(1.0)[:, None]).view(B, Z, Y, X, 3).permute(0, 4, 1, 2, 3)
        return build_mips(occupied.to(dt), radiance, (count > 0).to(dt).view(B, Z, Y, X))
