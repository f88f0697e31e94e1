"""`voxels.rounded`: each DDA hit refined inside a rounded voxel (`shade.rounded_refine`); a ray
that misses the rounded shape continues the DDA past its voxel, up to `rounded.retries` times."""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor

from ...schema.batch import Stacked, take
from ..dda import Hits, next_cell_lanes
from ..shade import rounded_refine
from ..tracer import VoxelTracer

__all__ = ["RoundedVoxels", "cell_exit"]


class RoundedVoxels:
    """The batch's rounded voxels (`voxels`: its `Stacked` voxels) in `tracer`'s grids."""

    def __init__(self, voxels: Stacked, tracer: VoxelTracer):
        self.p, self.tracer = voxels, tracer

    def __call__(self, o: Tensor, d: Tensor, s: Tensor, hits: Hits) -> tuple[Hits, Tensor]:
        """The DDA's `hits` of rays o, d [n, 3] of scenes s [n] refined -> (the rounded hits, their
        `steps` the DDA's plus the refinement's and the restarts'; the shading normals [n, 3])."""
        p, g, r = self.p, self.tracer.grid, self.p.rounded
        hit, t, cell, axis, mat = hits.hit.clone(), hits.t.clone(), hits.cell.clone(), hits.axis.clone(), hits.material.clone()
        normal = torch.zeros_like(o)
        extra = torch.zeros_like(hits.steps)
        pending = hit.nonzero().squeeze(1)
        hit[:] = False
        for attempt in range(r.retries + 1):
            if not pending.numel():
                break
            sp, dp, tp, cp = s[pending], d[pending], t[pending], cell[pending]
            size = g.voxel_size[sp]
            local = g.to_grid(o[pending] + tp[:, None] * dp, sp) - cp.to(o.dtype) - 0.5
            ok, adv, nrm = rounded_refine(local, dp, cp, radius_min=take(r.radius_min, sp), radius_range=take(r.radius_range, sp),
                                          steps=r.steps, threshold=take(r.threshold, sp), seed=r.seed)
            extra[pending] += r.steps
            good = pending[ok]
            hit[good] = True
            t[good] = tp[ok] + adv[ok] * size[ok]
            normal[good] = nrm[ok]
            miss = pending[~ok]
            if not miss.numel() or attempt == r.retries:
                break
            # continue past this voxel: restart just after its exit
            t_exit = cell_exit(g, o[miss], d[miss], s[miss], cell[miss])
            h2 = self.tracer.traverse(o[miss], d[miss], s[miss], max_steps=p.max_steps, t_min=t_exit, plain=True)
            # the restart must not re-enter the voxel it left (it starts just after t_exit)
            extra[miss] += h2.steps
            cell[miss], axis[miss], t[miss], mat[miss] = h2.cell, h2.axis, h2.t, h2.material
            pending = miss[h2.hit]
        return replace(hits, hit=hit, t=t, cell=cell, axis=axis, material=mat, steps=hits.steps + extra), normal


def cell_exit(grid, o: Tensor, d: Tensor, s: Tensor, cell: Tensor) -> Tensor:
    """Where world rays o, d [n, 3] of scenes s [n] leave their cells `cell` [n, 3] (long): the
    distance [n] to the DDA's next crossing (`dda.next_cell_lanes`)."""
    og, dg = grid.to_grid(o, s), d / grid.voxel_size[s, None]
    return next_cell_lanes(tuple(cell.unbind(1)), tuple(og.unbind(1)), tuple(dg.unbind(1)))[1]
