"""Empty-space skipping: where along each ray a medium with a known occupancy can be non-zero.

A grid medium knows which of its cells may hold density (`fields.grid.grid_occupancy`). Pooled to
at most `MACRO_CELLS` macro cells a side, each ray is sampled at a spacing just under one macro cell
on every axis: between two consecutive samples the cell index moves by at most one on every axis,
so the segment between them lies in the block of macro cells from the componentwise minimum of
their two cells, one or two cells wide on each axis as the samples' cells differ there.
`MacroGrid.blocks` says whether that block holds an occupied cell; the occupied span runs from the
start of the first such segment to the end of the last. It is conservative (every point with
density lies inside it, tested with hypothesis) and at most a segment looser than the exact
macro-cell span at each end. The march then samples only
inside it; samples outside would see σ = 0, so skipping changes the cost, never the result (the
march keeps its step lattice: see `march(occupied=...)`).

One gather per sample, in chunks of whole rays; docs/VOLUMES.md has its cost and tightness against
the alternatives tried (a hybrid DDA over macro cells, always testing the block from the lower cell).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..ops.grid_ops import dilate, pooled_max

MACRO_CELLS = 64  # along the longest axis: finer cells give a tighter span for more samples per ray
CHUNK_SAMPLES = 1 << 19  # samples per chunk: whole rays, ~2 MB per float32 temporary
SPACING = 0.99  # of a macro cell along the ray's fastest axis: rounding must never move a sample two cells on


@dataclass(frozen=True)
class MacroGrid:
    """`blocks` (8, D, H, W) bool: entry (δx + 2δy + 4δz, k, j, i) says whether any macro cell
    from (i, j, k) to (i + δx, j + δy, k + δz) is occupied (δ ∈ {0, 1}); macro cells of size
    `cell` [3] tile from the box's min corner."""

    blocks: Tensor
    cell: Tensor


def macro_grid(occupancy: Tensor, box_min: Tensor, box_max: Tensor, *, cells: int = MACRO_CELLS) -> MacroGrid:
    """`occupancy` (D, H, W) bool tiling the box [box_min, box_max] ([3] each), pooled by the integer
    factor that brings the longest axis to at most `cells`; a macro cell is occupied when any of its
    cells is. Where the factor does not divide a side the last macro cells reach past the box (they
    are as empty there as outside)."""
    pooled, factor = pooled_max(occupancy.to(torch.float32), cells=cells)
    pooled = pooled > 0
    fine = (box_max - box_min) / torch.tensor(occupancy.shape[::-1], dtype=box_min.dtype, device=box_min.device)
    blocks = [pooled]
    for axis in (2, 1, 0):  # x (the last tensor axis) is bit 1, y bit 2, z bit 4
        blocks = blocks + [dilate(b, before=0, after=1, axes=(axis,)) for b in blocks]
    return MacroGrid(blocks=torch.stack(blocks), cell=fine * factor)


def occupied_span(
    origins: Tensor, directions: Tensor, t0: Tensor, t1: Tensor, level: MacroGrid, box_min: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Per ray [R]: (t_first, t_last, any): a part of [t0, t1] that holds every point of the ray in
    an occupied macro cell of `level`, which tiles from the corner `box_min` [3]; `origins`,
    `directions` [R, 3]. Where `any` is False the ray meets no occupied cell."""
    depth, height, width = level.blocks.shape[1:]
    first, last = t0.clone(), t0.clone()
    found = torch.zeros_like(t0, dtype=torch.bool)
    if t0.numel() == 0:
        return first, last, found
    # [R] in t: under one macro cell on every axis. Per axis, so that a ray's sample count stays
    # under ~its macro cells crossed even in a box that is thin along some axis (R·S stays bounded)
    spacing = SPACING * (level.cell / directions.abs()).amin(dim=1)
    samples = int(torch.ceil(((t1 - t0) / spacing).max()).clamp_min(1)) + 1
    k = torch.arange(samples, dtype=t0.dtype, device=t0.device)
    grid_o, grid_d = (origins - box_min) / level.cell, directions / level.cell
    flat = level.blocks.reshape(-1)
    top, stride = (width - 1, height - 1, depth - 1), (1.0, float(width), float(width * height))
    cells = float(depth * height * width)
    rows = max(1, CHUNK_SAMPLES // samples)
    for a in range(0, t0.shape[0], rows):
        r = slice(a, a + rows)
        t = torch.minimum(torch.addcmul(t0[r, None], k, spacing[r, None]), t1[r, None])  # [n, S]
        block = None  # [n, S − 1]: flat index of each segment's block, built axis by axis in place
        for axis in range(3):
            c = torch.addcmul(grid_o[r, axis, None], t, grid_d[r, axis, None]).floor_().clamp_(0, top[axis])
            step = c[:, 1:] - c[:, :-1]  # −1, 0 or 1: where the segment's end cells differ, the block is two cells wide
            index = (c[:, :-1] + step.clamp_max(0.0)).mul_(stride[axis])  # the lower of the two cells
            index.add_(step.abs_(), alpha=float(1 << axis) * cells)
            block = index if block is None else block.add_(index)
        occupied = flat[block.long()]  # [n, S − 1]: segment s = [t_s, t_s+1] may meet density
        hits = occupied.to(torch.uint8)
        found[r] = occupied.any(dim=1)
        first[r] = t.gather(1, hits.argmax(dim=1, keepdim=True))[:, 0]
        last[r] = t.gather(1, samples - 1 - hits.flip(1).argmax(dim=1, keepdim=True))[:, 0]
    first, last = torch.where(found, first, t0), torch.where(found, last, t0)
    return first, last, found
