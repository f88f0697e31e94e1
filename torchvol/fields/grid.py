"""A cell-centred density grid spanning a box: trilinear, clamped to the edge inside, 0 outside.

grid[k, j, i] is the value at the centre of cell (i, j, k) (i along x, j along y, k along z), which
is `grid_sample`'s align_corners=False convention with border padding. The lookup is written once,
in lanes (`grid_density`, `grid_sample`'s own arithmetic: its index, clip, weights and sum in its
order) over the batch's grids flattened into one table (`grid_lanes`): the eager field runs it on
torch columns, the kernels trace it. `sample_grid` (torch's `grid_sample` itself) is the outside
oracle the tests hold it to bitwise, and the exact references' lookup (`volume/exact.py`).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..noise.lattice import _CORNERS
from ..ops import lanes
from ..ops.grid_ops import dilate, pooled_max, sliding_max
from ..schema.batch import Stacked
from ..schema.models import GridSource
from .base import torch_inputs


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
    hands them over, since a grid spans its volume's box. A batch may hold grids of different
    shapes (`data` is a per-scene value): `flat` [Σ cells] holds them one after the other, each
    scene's from `first` (B,) int32, `grids` (D, H, W) views of it; `cells` (B, 3) their cells
    along x, y, z."""

    def __init__(self, params: Stacked, times: Tensor, *, box_min: Tensor, box_max: Tensor):
        sizes = [a.size for a in params.data]
        self.flat = torch.cat([torch.as_tensor(a, dtype=times.dtype, device=times.device).reshape(-1) for a in params.data])
        self.grids = [part.view(a.shape) for part, a in zip(self.flat.split(sizes), params.data)]
        self.first = torch.tensor([0, *np.cumsum(sizes)[:-1]], dtype=torch.int32, device=times.device)
        self.box_min, self.box_max = box_min, box_max
        self.cells = torch.tensor([a.shape[::-1] for a in params.data], dtype=times.dtype, device=times.device)
        self.feature_size = ((box_max - box_min) / self.cells).amin(dim=1)

    def occupancy(self, b: int) -> Tensor:
        """Scene b's `grid_occupancy`: computed on demand, the skip pass keeps what it builds from it."""
        return grid_occupancy(self.grids[b])

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        """The density at points [n, 3] of scenes scene_index [n] -> [n]: `grid_density` on torch
        columns, the lookup the kernels trace."""
        return grid_density(grid_lanes(self, torch_inputs(scene_index)), list(points.unbind(1)), None)

    signed = __call__  # never clamped: the density is its own signed value


def grid_macro(field: Grid, b: int, low: Tensor, high: Tensor, cells: int) -> tuple[Tensor, Tensor, Tensor]:
    """Scene b's grid's local majorants (`volume.local_majorant`, `macro_bounds`); its own box
    (`low`, `high`, the volume's: the same) tiles them."""
    return macro_bounds(field.grids[b], field.box_min[b], field.box_max[b], cells=cells)


def macro_bounds(grid: Tensor, box_min: Tensor, box_max: Tensor, *, cells: int) -> tuple[Tensor, Tensor, Tensor]:
    """A grid (D, H, W) over the box [box_min, box_max] ([3] each) pooled to at most `cells` macro
    cells a side (`grid_ops.pooled_max`), each one's bound the largest of the values its points
    blend (the trilinear lookup in cell i blends the centres i − 1 … i + 1: exact) -> (bounds
    (D', H', W'), their corner [3], size [3]; the last may reach past the box)."""
    macro, factor = pooled_max(sliding_max(grid, 3, pad=1), cells=cells)
    size = (box_max - box_min) / torch.tensor(grid.shape[::-1], dtype=box_min.dtype, device=box_min.device) * factor
    return macro, box_min, size


def grid_lanes(field: Grid, to) -> SimpleNamespace:
    """What the lookup takes per lane (`to`: as `fields.DENSITIES`' ``lanes`` inputs): the batch's
    grids as one table (`to.floats`), the first cell of each lane's scene in it (`to.ints`), its
    cells along x, y, z and its box (three lanes each, `to.per_lane`)."""
    return SimpleNamespace(table=to.floats(field.flat), first=to.ints(field.first[to.scene]), cells=to.per_lane(field.cells),
                           box_min=to.per_lane(field.box_min), box_max=to.per_lane(field.box_max))


def grid_density(q, p, count):
    """The grid's value at p (three lanes), `q` from `grid_lanes` (`count` does not apply), in
    lanes (`ops.lanes`) as `sample_grid` computes it, operation for operation: the point in the
    box's unit cube, `grid_sample`'s source index ((2u − 1 + 1)·n − 1)/2, clipped to [0, n − 1]
    (border padding: the edge cell's value from its centre out to the face), the 8 corners'
    weights as products of their axes' and the sum in `grid_sample`'s corner order; 0 outside
    the box, its faces inside. A corner past the last cell (at the clipped n − 1 exactly) has
    weight 0: its index is clamped to the last cell, where `grid_sample` skips it."""
    inside, index, weights = None, [], []
    for a in range(3):
        unit = (p[a] - q.box_min[a]) / (q.box_max[a] - q.box_min[a])
        x = (((2.0 * unit - 1.0) + 1.0) * q.cells[a] - 1.0) * 0.5
        # clipped with selects: NaN goes to 0, so every gather stays in the table (`inside` zeroes it)
        x = lanes.where(x < q.cells[a] - 1.0, lanes.where(x > 0.0, x, 0.0), q.cells[a] - 1.0)
        lo = lanes.floor(x)
        i = lanes.to_int32(lo)
        index.append((i, lanes.minimum(i + 1, lanes.to_int32(q.cells[a]) - 1)))
        weights.append((lo + 1.0 - x, x - lo))
        ok = (unit >= 0.0) & (unit <= 1.0)
        inside = ok if inside is None else inside & ok
    width, height = lanes.to_int32(q.cells[0]), lanes.to_int32(q.cells[1])
    total = 0.0
    for cx, cy, cz in _CORNERS:
        at = q.first + (index[2][cz] * height + index[1][cy]) * width + index[0][cx]
        total = total + lanes.gather(q.table, at) * (weights[0][cx] * weights[1][cy] * weights[2][cz])
    return lanes.where(inside, total, 0.0)
