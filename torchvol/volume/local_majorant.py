"""Local majorants of a medium for the path tracer's tracking (`path.track_lanes`).

One majorant per medium makes delta tracking take a null collision every 1/σ̄ along a ray, so a
cloud whose densest voxel is 4× its mean pays ~3 density evaluations for each real collision,
and more in the empty corners of its box. Here the medium's box is cut into macro cells (at most
`CELLS_MAX` along its longest side, fewer where the medium is thin: `macro_cells`), each with a
bound of the density over it from its density kind (`fields.DENSITIES`' ``macro``: a grid's
exact, from the cell centres its trilinear lookup blends; value-noise fbm's from its lattice; an
exponential profile's in slabs). Each macro cell holds the largest bound over the 3³ block of
macro cells about it, which bounds the density on any segment from any point of the cell that
moves less than a macro cell along every axis: along a direction d, as far as the least of
size_a/|d_a| (times `REACH`), its `reach`. Where that block is empty, it holds as many cells on
as the nearest macro cell with density is away (Chebyshev, less one). The tracking looks
the bound up where it stands, draws a free flight against it and, where the flight passes the
reach, moves there without a collision and looks again: an exponential restarts at any point, so
this is delta tracking against a piecewise-constant majorant, unbiased for any bound that holds
(docs/VOLUMES.md, `[path]`).
"""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import torch
from torch import Tensor

from ..ops import lanes
from ..ops.grid_ops import chebyshev_distance, sliding_max

CELLS_MAX = 16  # macro cells along a box's longest side at most (finer cells restart flights more often)
CELL_DEPTH = 1.5  # the optical depth of the one majorant across a macro cell, at least (`macro_cells`)
REACH = 0.99  # of a macro cell's smallest side: a point rounded past its cell's face stays within the block
_ABOVE = 1.0 + 2.0**-20  # a float32 trilinear sum may round a hair above its largest corner


@dataclass(frozen=True)
class MacroMajorant:
    """The local majorants of a medium in B scenes: `bound` [Σ cells] the largest density over each
    macro cell's 3³ block, `cells_on` [Σ cells] for how many macro cells along every axis from any
    point of the cell it holds (times `REACH`), each
    scene's from `first` (B,) int32, its macro `cells` (B, 3) along x, y, z (float) tiling from
    `box_min` (B, 3) in steps of `size` (B, 3)."""

    bound: Tensor
    cells_on: Tensor
    first: Tensor
    cells: Tensor
    box_min: Tensor
    size: Tensor


def macro_cells(majorant: Tensor, box_min: Tensor, box_max: Tensor) -> list[int]:
    """How many macro cells along its box's longest side each scene's medium takes: its one majorant (B,) times
    its box's longest side ((B, 3) corners) over `CELL_DEPTH`, within 1 … `CELLS_MAX`. A flight
    restarts at each macro cell it crosses, so where the whole box is a few mean free paths of its
    majorant deep the macro cells would cost more restarts than they save null collisions."""
    depth = majorant * (box_max - box_min).amax(dim=1) / CELL_DEPTH
    return [int(c) for c in depth.ceil().clamp(1, CELLS_MAX).tolist()]


def macro_majorant(parts: list[tuple[Tensor, Tensor, Tensor]]) -> MacroMajorant:
    """The local majorants of B scenes from each one's macro cells `parts[b]` = (bounds (D, H, W)
    = [k, j, i] of the density over each cell, the cells' corner [3] and size [3]): each cell's
    bound the largest over the 3³ block about it, holding one macro cell on (× `REACH`), or
    where that block is empty, that times the Chebyshev distance to the nearest cell with density
    less one."""
    bounds, cells_on, shapes = [], [], []
    for macro, _, size in parts:
        block = sliding_max(macro, 3, pad=1)
        steps = chebyshev_distance(macro > 0, max_radius=max(block.shape) + 1).to(block.dtype)
        bounds.append(block.reshape(-1) * _ABOVE)
        cells_on.append((steps - 1.0).clamp_min(1.0).reshape(-1) * REACH)
        shapes.append(block.shape[::-1])
    counts = [x.numel() for x in bounds]
    like = parts[0][1]
    first = torch.tensor([sum(counts[:b]) for b in range(len(counts))], dtype=torch.int32, device=like.device)
    return MacroMajorant(bound=torch.cat(bounds), cells_on=torch.cat(cells_on), first=first,
                         cells=torch.tensor(shapes, dtype=like.dtype, device=like.device),
                         box_min=torch.stack([p[1] for p in parts]), size=torch.stack([p[2] for p in parts]))


def macro_lanes(m: MacroMajorant, to) -> SimpleNamespace:
    """What `bound_at` takes per lane (`to`: as `fields.DENSITIES`' ``lanes`` inputs): the tables
    (`to.floats`), each lane's scene's first macro cell (`to.ints`), its cells, box corner and
    macro cell size (three lanes each, `to.per_lane`)."""
    return SimpleNamespace(bound=to.floats(m.bound), cells_on=to.floats(m.cells_on), first=to.ints(m.first[to.scene]),
                           cells=to.per_lane(m.cells), box_min=to.per_lane(m.box_min), size=to.per_lane(m.size))


def bound_at(q, p, d) -> tuple:
    """(the density's bound, how far along d it holds) at points p along directions d (three
    lanes each) of the macro cells `q` (`macro_lanes`), lanes: as many cells on as the cell's
    `cells_on`, along d the least of size_a/|d_a| each (a unit d: at least the smallest side); a
    point outside its box takes the nearest macro cell's."""
    at, across = None, None
    for a in (2, 1, 0):
        x = (p[a] - q.box_min[a]) / q.size[a]
        x = lanes.where(x < q.cells[a] - 1.0, lanes.where(x > 0.0, x, 0.0), q.cells[a] - 1.0)  # NaN -> 0
        i = lanes.to_int32(lanes.floor(x))
        at = i if at is None else at * lanes.to_int32(q.cells[a]) + i
        along = q.size[a] / lanes.abs(d[a])  # inf along an axis d does not move on
        across = along if across is None else lanes.minimum(across, along)
    at = q.first + at
    return lanes.gather(q.bound, at), lanes.gather(q.cells_on, at) * across


__all__ = ["CELLS_MAX", "CELL_DEPTH", "REACH", "MacroMajorant", "bound_at", "macro_cells", "macro_lanes", "macro_majorant"]
