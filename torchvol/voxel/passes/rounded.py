"""`voxels.rounded`: each DDA hit refined inside a rounded voxel; a ray that misses the rounded
shape continues the DDA past its voxel, up to `rounded.retries` times. The walk is
`walk.rounded_walk`, the path tracer's too: one Dr.Jit kernel a chunk where the tracer's walks are
kernels, else the same lanes on torch columns (the reference)."""

from __future__ import annotations

import math
from dataclasses import replace

import torch
from torch import Tensor

from ...ops import lanes
from ...ops.mathops import take_rows
from ...runtime.threads import set_drjit_threads
from ...schema.batch import Stacked, take
from ..dda import Hits, next_cell_lanes
from ..tracer import VoxelTracer
from ..walk import cube_walk, rounded_walk, walk_inputs

__all__ = ["RoundedVoxels", "cell_exit"]


class RoundedVoxels:
    """The batch's rounded voxels (`voxels`: its `Stacked` voxels) in `tracer`'s grids."""

    def __init__(self, voxels: Stacked, tracer: VoxelTracer):
        self.p, self.tracer = voxels, tracer

    def __call__(self, o: Tensor, d: Tensor, s: Tensor, hits: Hits) -> tuple[Hits, Tensor]:
        """The DDA's `hits` of rays o, d [n, 3] of scenes s [n] refined -> (the rounded hits, their
        `steps` the DDA's plus the refinement's and the restarts'; the shading normals [n, 3])."""
        ids = hits.hit.nonzero().squeeze(1)
        hit, normal = torch.zeros_like(hits.hit), torch.zeros_like(o)
        if not ids.numel():
            return replace(hits, hit=hit), normal
        kernel, sh = self.tracer.drjit, take_rows(s, ids)
        if kernel:
            set_drjit_threads()
            ints, floats, per_lane = lanes.ints_of, lanes.floats_of, lanes.per_scene_lanes(sh)
        else:
            ints, floats, per_lane = (lambda x: x.to(torch.int32)), (lambda x: x), (lambda v: lanes.columns(take(v, sh)))
        r, g = walk_inputs(self.tracer.grid, sh, per_lane, ints, kernel=kernel, max_steps=int(self.p.max_steps))
        ow, dw = ([floats(c) for c in take_rows(x, ids).unbind(1)] for x in (o, d))
        material = ints(take_rows(hits.material, ids))
        first = (material > 0, floats(take_rows(hits.t, ids)), ints(take_rows(hits.axis, ids)), material,
                 (None, [ints(c) for c in take_rows(hits.cell, ids).unbind(1)]), None, None)
        walk = rounded_walk(cube_walk(r, g), r, self.p.rounded, per_lane, kernel=kernel)
        found, t, axis, material, (_, cell), nrm, extra = walk(ow, dw, ow[0] * 0.0 + math.inf, first=first)
        out = [found, t, axis, material, *cell, *nrm, extra]
        if kernel:
            import drjit as dr

            dr.eval(out)
            dr.sync_thread()
            out = [lanes.tensor_of(v).to(o.device) for v in out]
        found, t, axis, material, cx, cy, cz, nx, ny, nz, extra = out
        kept = found.nonzero().squeeze(1)
        good = take_rows(ids, kept)
        on = lambda x: take_rows(x, kept)  # noqa: E731
        hit[good] = True
        normal[good] = torch.stack([on(nx), on(ny), on(nz)], 1).to(o.dtype)
        refined = {"t": hits.t.clone(), "cell": hits.cell.clone(), "axis": hits.axis.clone(), "material": hits.material.clone()}
        for key, value in (("t", on(t).to(o.dtype)), ("cell", torch.stack([on(cx), on(cy), on(cz)], 1).long()),
                           ("axis", on(axis).long()), ("material", on(material).long())):
            refined[key][good] = value
        steps = hits.steps.index_add(0, ids, extra.to(hits.steps.dtype))
        return replace(hits, hit=hit, steps=steps, **refined), normal


def cell_exit(grid, o: Tensor, d: Tensor, s: Tensor, cell: Tensor) -> Tensor:
    """Where world rays o, d [n, 3] of scenes s [n] leave their cells `cell` [n, 3] (long): the
    distance [n] to the DDA's next crossing (`dda.next_cell_lanes`)."""
    og, dg = grid.to_grid(o, s), d / grid.voxel_size[s, None]
    return next_cell_lanes(tuple(cell.unbind(1)), tuple(og.unbind(1)), tuple(dg.unbind(1)))[1]
