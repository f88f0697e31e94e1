"""The voxel fog's extinction: exponential height fog over the cells a primary ray walks through
(`voxels.fog`), one formula for the eager per-cell callback (`passes/fog.py`) and the table the
Dr.Jit walk gathers from (`walk.walk_step`), so the two give the same bits; the glow's per-cell
term likewise one table (`GlowWalk`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["FogWalk", "GlowWalk", "extinction"]


def extinction(y: Tensor, density: Tensor, base: Tensor, scale_height: Tensor) -> Tensor:
    """σ [m] at heights y [m]: density · exp(−(y − base) / scale_height); all [m]."""
    return density * torch.exp(-(y - base) / scale_height)


@dataclass
class FogWalk:
    """The fog the Dr.Jit walk accumulates (`walk.drjit_traverse(..., fog=)`).

    A cell's σ depends on its scene and its row of cells alone, so the walk gathers it from
    `table` [B·Y] (σ at the centre of cell row j of scene b at b·Y + j − lo_y) by `rows` [R] long
    (each ray's b·Y − lo_y): the kernel has no exp of its own for σ, which is eager's to the bit.
    Filled by the walk: tau [R], each ray's optical depth to where it ended, and `light` [R, 3],
    from `irradiance(flat cell indices [u]) -> [u, 3]` (the light reaching those cells' centres,
    asked once for every distinct empty cell the rays visited) times `color` [R, 3]."""

    rows: Tensor
    table: Tensor
    tau: Tensor | None = None
    irradiance: Callable[[Tensor], Tensor] | None = None
    color: Tensor | None = None
    light: Tensor | None = None


@dataclass
class GlowWalk:
    """The glow the Dr.Jit walk accumulates (`walk.drjit_traverse(..., glow=)`): a visited cell's
    term depends on the cell alone, so the walk gathers it from `table` [M] (indexed as the
    flattened material grids; `passes.fog.FogGlow.glow_table`), the table the eager callback
    reads too. Filled by the walk: total [R], each ray's sum over the cells it visited."""

    table: Tensor
    total: Tensor | None = None
