"""Voxel shading as Dr.Jit kernels: the seeds' per-hit shading functions (`voxel.shade`, written in
lanes) traced over a chunk's hits, the grid looked up in the kernel (`walk.int_table`'s flattened
material grids). Chosen where the walk is a kernel (`VoxelTracer.drjit`); the eager functions are
the reference (tests/voxel/test_shade_kernel.py)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch
from torch import Tensor

from ..runtime.threads import set_drjit_threads
from .shade import ao_lanes

__all__ = ["ao_kernel"]


def ao_kernel(table, base: Tensor, strides: Tensor, lo: Tensor, hi: Tensor, cell: Tensor, normal: Tensor,
              axis: Tensor, uv: Tensor, gamma: Tensor) -> Tensor:
    """`shade.voxel_ao` of N hits as one Dr.Jit kernel: `table` the flattened material grids (an
    `int_table`), cell (i, j, k) of hit n at ``base[n] + (k·Y + j)·X + i`` (`VoxelGrid.flat_base`:
    base [N] long, strides (Y, X)), inside [lo, hi) [N, 3] long; cell [N, 3] long, normal [N, 3],
    axis [N], uv [N, 2], gamma [N]. -> [N] in uv's dtype (its exp and log Dr.Jit's: within float
    rounding of eager's)."""
    import drjit as dr
    from drjit.llvm import Float, Int32

    if cell.shape[0] == 0:
        return uv.new_zeros(0)
    set_drjit_threads()
    ints = lambda x: Int32(x.to(torch.int32).contiguous().cpu().numpy())  # noqa: E731
    floats = lambda x: Float(x.to(torch.float32).contiguous().cpu().numpy())  # noqa: E731
    g = SimpleNamespace(base=ints(base), y=int(strides[0]), x=int(strides[1]), lo=[ints(c) for c in lo.unbind(1)],
                        hi=[ints(c) for c in hi.unbind(1)])

    def occupied(x, y, z):
        inside = ((x >= g.lo[0]) & (x < g.hi[0]) & (y >= g.lo[1]) & (y < g.hi[1]) & (z >= g.lo[2])
                  & (z < g.hi[2]))
        mat = dr.gather(Int32, table, dr.select(inside, g.base + (z * g.y + y) * g.x + x, 0), inside)
        return dr.select(mat > 0, Float(1.0), Float(0.0))

    ao = ao_lanes(occupied, [ints(c) for c in cell.unbind(1)], [ints(c) for c in normal.unbind(1)], ints(axis),
                  floats(uv[:, 0]), floats(uv[:, 1]), floats(gamma))
    dr.eval(ao)
    dr.sync_thread()
    return torch.from_numpy(np.array(ao)).to(uv)
