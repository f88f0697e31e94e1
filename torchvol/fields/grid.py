"""A cell-centred density grid spanning a box: trilinear, clamped to the edge inside, 0 outside.

grid[k, j, i] is the value at the centre of cell (i, j, k) (i along x, j along y, k along z), which
is `grid_sample`'s align_corners=False convention with border padding.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..ops.grid_ops import dilate
from ..schema.batch import Stacked, per_scene
from ..schema.models import GridSource


class GridDensity(GridSource):
    """grid[k, j, i] is the value at the centre of cell (i, j, k) of the volume's box."""

    def _check(self, array: np.ndarray) -> np.ndarray:
        if not np.issubdtype(array.dtype, np.number) or not np.all(np.isfinite(array)) or array.min() < 0:
            raise ValueError("grid values must be finite numbers >= 0")
        return array.astype(np.float64, copy=False)


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
    """The grids of B scenes over their volumes' boxes (`box_min`, `box_max` (B, 3)): the renderer
    hands them over, since a grid spans its volume's box."""

    def __init__(self, params: Stacked, times: Tensor, *, box_min: Tensor, box_max: Tensor):
        self.grids = [torch.as_tensor(a, dtype=times.dtype, device=times.device) for a in params.data]
        self.box_min, self.box_max = box_min, box_max
        cells = torch.tensor([a.shape[::-1] for a in params.data], dtype=times.dtype, device=times.device)  # (B, 3) along x, y, z
        self.feature_size = ((box_max - box_min) / cells).amin(dim=1)

    def occupancy(self, b: int) -> Tensor:
        """Scene b's `grid_occupancy`: computed on demand, the skip pass keeps what it builds from it."""
        return grid_occupancy(self.grids[b])

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        return per_scene(
            points, scene_index, len(self.grids),
            lambda b, _, p: sample_grid(self.grids[b], self.box_min[b], self.box_max[b], p),
        )

    signed = __call__  # never clamped: the density is its own signed value
