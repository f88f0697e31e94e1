"""`voxels.gi`'s path-traced bounces (the default method): from each hit, cosine-weighted paths
through the DDA, each bounce lit by the direct light (diffuse) and the sky where a path leaves the
grid; their mean replaces the ambient. The path maths (hash keys, directions, LOD) is `gi.py`'s."""

from __future__ import annotations

from contextlib import nullcontext
from typing import Callable

import torch
from torch import Tensor

from ...schema.batch import Stacked, take
from ..gi import bounce_uniforms, cosine_directions, lod_counts, lod_keys, path_keys
from ..tracer import VoxelTracer
from .direct import DirectLight
from .point import ShadingPoint
from .shading import Shading

__all__ = ["PathGI"]


class PathGI:
    """The batch's GI paths (`voxels`: its `Stacked` voxels; `plan` its `VoxelPass`) traced by
    `tracer`, their hits shaded by `shading` and lit by `direct`; `sky(directions [n, 3], s [n])
    -> [n, 3]` what paths that leave the grid see (None: black)."""

    def __init__(self, voxels: Stacked, plan, tracer: VoxelTracer, shading: Shading, direct: DirectLight,
                 sky: Callable[[Tensor, Tensor], Tensor] | None):
        self.p, self.plan, self.tracer, self.shading, self.direct, self.sky = voxels, plan, tracer, shading, direct, sky

    def __call__(self, point: ShadingPoint, s: Tensor, keys: Tensor, distance: Tensor) -> Tensor:
        """The mean incoming radiance [n, 3] of `voxels.gi`'s paths from the hits `point`
        (scenes s [n], hash keys [n, 3], camera distance [n]): cosine-weighted, so the estimate is
        the plain path mean."""
        gi, n = self.p.gi, s.shape[0]
        S = gi.samples
        if gi.lod is None:
            cells, owner = path_keys(keys, S), None
            ps = s.repeat_interleave(S)
            x, normal = point.x.repeat_interleave(S, dim=0), point.face_normal.repeat_interleave(S, dim=0)
        else:
            counts = lod_counts(distance, S, take(gi.lod.near, s), take(gi.lod.far, s), gi.lod.samples)
            cells, owner = lod_keys(keys, counts, S)
            ps, x, normal = s[owner], point.x[owner], point.face_normal[owner]
        radiance, throughput = torch.zeros_like(x), torch.ones_like(x)
        alive = torch.arange(x.shape[0], device=x.device)
        # start a thousandth of a voxel off the face so the DDA starts in the empty cell in front of it
        eps = 1e-3 * self.tracer.grid.voxel_size
        for bounce in range(gi.bounces):
            sa = ps[alive]
            d = cosine_directions(normal, *bounce_uniforms(cells[alive], bounce, x.dtype))
            o = x + eps[sa, None] * normal
            h = self.tracer.traverse(o, d, sa, max_steps=self.p.max_steps, plain=True)
            self.tracer.count(h.steps)
            if self.sky is not None:
                miss = (~h.hit).nonzero().squeeze(1)
                radiance.index_add_(0, alive[miss], throughput[alive[miss]] * self.sky(d[miss], sa[miss]))
            keep = h.hit.nonzero().squeeze(1)
            alive, sa = alive[keep], sa[keep]
            if not alive.numel():
                break
            hit = self.shading.point(o[keep], d[keep], h.t[keep], h.cell[keep], h.axis[keep], h.material[keep], sa, None)
            incoming, _ = self.direct(hit, sa, lambda name: nullcontext(), torch.zeros_like(hit.x))  # paths see diffuse light
            own = hit.albedo * incoming
            if self.plan.emission:
                own = own + hit.emission
            radiance.index_add_(0, alive, throughput[alive] * own)
            throughput[alive] = throughput[alive] * hit.albedo
            x, normal = hit.x, hit.face_normal
        if owner is None:
            return radiance.view(n, S, 3).mean(dim=1)
        return torch.zeros_like(point.x).index_add_(0, owner, radiance) / counts[:, None].to(radiance.dtype)
