"""A cell-centred density grid spanning a box: trilinear, clamped to the edge inside, 0 outside.

grid[k, j, i] is the value at the centre of cell (i, j, k) (i along x, j along y, k along z), which
is `grid_sample`'s align_corners=False convention with border padding.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..voxel.dda import dilate
from .base import per_scene


def sample_grid(grid: Tensor, box_min: Tensor, box_max: Tensor, points: Tensor) -> Tensor:
    """`grid`: (D, H, W) = [k, j, i]; `box_min`, `box_max`: [3]; `points`: [N, 3] -> [N]."""
    unit = (points - box_min) / (box_max - box_min)  # [N, 3] in [0, 1] inside the box
    coords = (2.0 * unit - 1.0).reshape(1, 1, 1, -1, 3)  # grid_sample wants (x, y, z) = (i, j, k)
    value = F.grid_sample(grid[None, None], coords, mode="bilinear", padding_mode="border", align_corners=False)
    inside = ((unit >= 0) & (unit <= 1)).all(dim=1)
    return torch.where(inside, value.reshape(-1), torch.zeros_like(unit[:, 0]))


def grid_occupancy(grid: Tensor) -> Tensor:
    """Cells (D, H, W) bool where the trilinear density may be non-zero. Inside cell i the
    interpolation blends the values at cell centres i − 1, i, i + 1: a 3-wide dilation of grid > 0."""
    return dilate(grid > 0)


class Grid:
    homogeneous = False

    def __init__(self, arrays: Sequence[np.ndarray], boxes: Sequence, *, dtype, device):
        self.grids = [torch.as_tensor(a, dtype=dtype, device=device) for a in arrays]
        self.box_min = torch.tensor([b.min for b in boxes], dtype=dtype, device=device)  # (B, 3)
        self.box_max = torch.tensor([b.max for b in boxes], dtype=dtype, device=device)
        cells = torch.tensor([a.shape[::-1] for a in arrays], dtype=dtype, device=device)  # (B, 3) cells along x, y, z
        self.feature_size = ((self.box_max - self.box_min) / cells).amin(dim=1)

    def occupancy(self, b: int) -> Tensor:
        """Scene b's `grid_occupancy`: computed on demand, the skip pass keeps what it builds from it."""
        return grid_occupancy(self.grids[b])

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        return per_scene(
            points, scene_index, len(self.grids),
            lambda b, _, p: sample_grid(self.grids[b], self.box_min[b], self.box_max[b], p),
        )

    signed = __call__  # never clamped: the density is its own signed value
