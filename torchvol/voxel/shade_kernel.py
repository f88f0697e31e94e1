"""Voxel shading as Dr.Jit kernels: the seeds' per-hit shading functions (`voxel.shade`, written in
lanes) traced over a chunk's hits, the grid looked up in the kernel (`walk.int_table`'s flattened
material grids). Chosen where the walk is a kernel (`VoxelTracer.drjit`); the eager functions are
the reference (tests/voxel/test_shade_kernel.py)."""

from __future__ import annotations

from types import SimpleNamespace

import torch
from torch import Tensor

from ..ops import lanes
from ..runtime.threads import set_drjit_threads
from .cone import cone_step
from .shade import ao_lanes
from .walk import cell_ranges, occupied_lanes

__all__ = ["ao_kernel", "cones_kernel", "mips_lanes"]


def ao_kernel(table, base: Tensor, strides: Tensor, lo: Tensor, hi: Tensor, cell: Tensor, normal: Tensor,
              axis: Tensor, uv: Tensor, gamma: Tensor, scene: Tensor | None = None) -> Tensor:
    """`shade.voxel_ao` of N hits as one Dr.Jit kernel: `table` the flattened material grids (an
    `int_table`), cell (i, j, k) of hit n at ``base[n] + (k·Y + j)·X + i`` (`VoxelGrid.flat_base`:
    base [N] long, strides (Y, X)), inside [lo, hi) [N, 3] long (with `scene` [N]: base (B,) and
    lo, hi (B, 3) of each hit's scene, `walk.cell_ranges`); cell [N, 3] long, normal [N, 3], axis
    [N], uv [N, 2], gamma [N]. -> [N] in uv's dtype (its exp and log Dr.Jit's: within float
    rounding of eager's)."""
    import drjit as dr

    if cell.shape[0] == 0:
        return uv.new_zeros(0)
    set_drjit_threads()
    ints = lanes.ints_of
    floats = lanes.floats_of
    lo, hi, base = cell_ranges(lo, hi, base, scene, cell.shape[0], cell.device)
    occupied = occupied_lanes(SimpleNamespace(lo=lo, hi=hi, base=base),
                              SimpleNamespace(table=table, y=int(strides[0]), x=int(strides[1])))
    ao = ao_lanes(occupied, [ints(c) for c in cell.unbind(1)], [ints(c) for c in normal.unbind(1)], ints(axis),
                  floats(uv[:, 0]), floats(uv[:, 1]), floats(gamma))
    dr.eval(ao)
    dr.sync_thread()
    return lanes.tensor_of(ao).to(uv)


def mips_lanes(table: Tensor, offsets: list[int], sizes: list[int]) -> SimpleNamespace:
    """A mip chain (`cone.mip_table`'s table [M], level offsets and sizes) as `cone.cone_step` takes
    it in a kernel: Dr.Jit arrays, built once a render."""
    import drjit as dr
    from drjit.llvm import Float, Int32

    flat, offset, size = Float(table.to(torch.float32).cpu().numpy()), Int32(offsets), Int32(sizes)
    return SimpleNamespace(table=flat, top=len(sizes) - 1, size=sizes[0],
                           gather_level=lambda lvl: (dr.gather(Int32, offset, lvl), dr.gather(Int32, size, lvl)))


def cones_kernel(mips: SimpleNamespace, origin: Tensor, direction: Tensor, s: Tensor, ratio: Tensor, *, steps: int,
                 max_t: Tensor) -> tuple[Tensor, Tensor]:
    """`cone.trace_cones` as one Dr.Jit kernel: each cone's march a loop of `cone.cone_step`
    (`mips`: `mips_lanes`). origin, direction [n, 3]; s, ratio, max_t [n]. -> (radiance [n, 3],
    occlusion [n]) in origin's dtype (Dr.Jit's exp, log and log2: within float rounding of eager's)."""
    import drjit as dr
    from drjit.llvm import Bool, Float, Int32

    n = origin.shape[0]
    if n == 0:
        return origin.new_zeros(0, 3), origin.new_zeros(0)
    set_drjit_threads()
    floats = lanes.floats_of
    ray = SimpleNamespace(o=[floats(c) for c in origin.unbind(1)], d=[floats(c) for c in direction.unbind(1)],
                          s=lanes.ints_of(s), ratio=floats(ratio), max_t=floats(max_t))
    limit = dr.opaque(Int32, steps)
    state = (dr.full(Float, 1.0, n), dr.zeros(Float, n), dr.zeros(Float, n), dr.zeros(Float, n), dr.zeros(Float, n),
             dr.full(Bool, True, n), dr.zeros(Int32, n))

    def body(*x):  # the seed's t = 1: the first sample a voxel out
        return (*cone_step(list(x[:6]), ray, mips), x[6] + 1)

    out = dr.while_loop(state, lambda *x: x[5] & (x[6] < limit), body, mode="symbolic")
    colour = lanes.interleaved(out[2:5])
    dr.eval(out[1], colour)  # (the colour as rows only)
    dr.sync_thread()
    return lanes.rows_of(colour, 3).to(origin), lanes.tensor_of(out[1]).to(origin)
