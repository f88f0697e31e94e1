"""Occupancy: dense material-id grids (uint8, 0 = empty) placed in the world by origin and voxel size.

Every occupancy kind of the scene schema becomes one dense grid over its integer cell range
``[lo, hi)`` (cell ``(i, j, k)`` spans ``origin + [i, i+1) · voxel_size`` etc.):

* ``grid``: the array itself, ``grid[k, j, i]`` for cell ``lo + (i, j, k)``;
* ``sdf``: `sdf.evaluate` at the world cell centres ``origin + (c + 0.5) · voxel_size`` — the seed's
  ``getVoxel`` (``d < 0`` occupied);
* ``terrain``: an fbm heightmap with grass / dirt / stone layers (`terrain_materials`), and optional
  sparse `ores` blocks near the surface (`ore_cells`);
* ``function``: any callable mapping integer cells ``[N, 3]`` to material ids ``[N]``.

`VoxelGrid` stacks the grids of B scenes (zero-padded to a common shape) so that one gather looks
up the cells of a flat ray batch, each ray in its own scene.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from ..geometry import sdf
from ..noise import lattice as noise
from ..ops.grid_ops import chebyshev_distance
from ..ops.mathops import take_rows

__all__ = ["VoxelGrid", "cell_range", "dense_materials", "ore_cells", "terrain_columns", "terrain_height", "terrain_heights", "terrain_materials", "cell_centres"]


def cell_range(spec) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
    """(lo, hi) integer cell range of a `Voxels` spec (a grid's own shape for grid occupancy)."""
    lo = tuple(spec.cells.min)
    if spec.occupancy.kind == "grid":
        z, y, x = spec.occupancy.grid.data.shape
        return lo, (lo[0] + x, lo[1] + y, lo[2] + z)
    return lo, tuple(spec.cells.max)


def _cells(lo, hi, device) -> Tensor:
    """All cells of [lo, hi) as [N, 3] long, in [k, j, i] (z-major) order."""
    axes = [torch.arange(lo[a], hi[a], device=device) for a in (2, 1, 0)]
    k, j, i = torch.meshgrid(*axes, indexing="ij")
    return torch.stack([i.reshape(-1), j.reshape(-1), k.reshape(-1)], dim=1)


def cell_centres(cells: Tensor, origin, voxel_size, dtype) -> Tensor:
    """World centres [N, 3] of integer cells [N, 3]: origin + (c + 0.5) · voxel_size."""
    o = torch.as_tensor(origin, dtype=dtype, device=cells.device)
    return o + (cells.to(dtype) + 0.5) * voxel_size


def terrain_height(x: Tensor, z: Tensor, spec) -> Tensor:
    """Heightmap [N] at cell columns x, z [N]: base + amplitude · Σ_k gain^k · value_noise_k."""
    return terrain_heights([(x, z, spec)])[0]


def terrain_heights(columns: Sequence[tuple[Tensor, Tensor, object]]) -> list[Tensor]:
    """`terrain_height` of several (x [N], z [N], spec) at once: every octave of every spec one
    block of a single `value_noise_scenes` call (the same values as one call each, ~0.2 ms of small
    ops apiece: a batch's grids drew 16 such calls)."""
    points, seeds, weights = [], [], []
    for x, z, spec in columns:
        freq, amp, amps = spec.frequency, 1.0, []
        for k in range(spec.octaves):
            points.append(torch.stack([x * freq, torch.full_like(x, 0.5), z * freq], dim=1))
            seeds.append(spec.seed * 131 + k)
            amps.append(amp)
            freq, amp = freq * spec.lacunarity, amp * spec.gain
        weights.append(amps)
    if not points:
        return []
    sizes = [q.shape[0] for q in points]
    block = torch.cat([torch.full((n,), i, device=points[0].device) for i, n in enumerate(sizes)])
    values = iter(noise.value_noise_scenes(torch.cat(points), noise.scene_rows(block), seeds).split(sizes))
    out = []
    for (x, _, spec), amps in zip(columns, weights):
        h = torch.zeros_like(x)
        for amp in amps:
            h = h + amp * next(values)
        out.append(spec.base + spec.amplitude * h)
    return out


def terrain_materials(cells: Tensor, spec, dtype=torch.float32) -> Tensor:
    """Material ids [N] (long) of cells [N, 3]: the seed's layers — air above h, grass within 1 below,
    dirt `dirt_depth` further, stone beneath."""
    h = terrain_height(cells[:, 0].to(dtype), cells[:, 2].to(dtype), spec)
    y = cells[:, 1].to(dtype)
    grass, dirt, stone = spec.materials
    out = torch.full_like(cells[:, 0], stone)
    out = torch.where(y > h - 1.0 - spec.dirt_depth, torch.full_like(out, dirt), out)
    out = torch.where(y > h - 1.0, torch.full_like(out, grass), out)
    if spec.ores is not None:
        out = torch.where(ore_cells(cells, h, spec.ores), torch.full_like(out, spec.ores.material), out)
    return torch.where(y > h, torch.zeros_like(out), out)


def ore_cells(cells: Tensor, h: Tensor, ores) -> Tensor:
    """Where [N] cells [N, 3] (long) under column heights h [N] hold the `ores` material: within
    `ores.depth` below the surface and hashed below `ores.density` (float64 hash: the same cells at
    any render dtype). Solidity (j ≤ h) is the caller's."""
    near = cells[:, 1].to(h.dtype) > h - ores.depth
    return near & (noise.hash3(cells, ores.seed, dtype=torch.float64) < ores.density)


def terrain_columns(spec, *, dtype, device) -> tuple[Tensor, Tensor, object]:
    """(x [Z·X], z [Z·X], terrain spec): the cell columns of a `Voxels` spec with terrain occupancy,
    z-major, as `terrain_heights` takes them."""
    lo, hi = cell_range(spec)
    z, x = torch.meshgrid(torch.arange(lo[2], hi[2], device=device), torch.arange(lo[0], hi[0], device=device), indexing="ij")
    return x.reshape(-1).to(dtype), z.reshape(-1).to(dtype), spec.occupancy.terrain


def dense_materials(spec, *, dtype=torch.float32, device="cpu", batch_cells: int = 1 << 22,
                    height: Tensor | None = None) -> Tensor:
    """The (Z, Y, X) uint8 material grid of one `Voxels` spec over its cell range; `height` [Z·X]
    its terrain's heights at `terrain_columns` where computed already (None: here)."""
    occ = spec.occupancy
    lo, hi = cell_range(spec)
    if occ.kind == "grid":
        return torch.as_tensor(occ.grid.data, device=device)
    shape = (hi[2] - lo[2], hi[1] - lo[1], hi[0] - lo[0])
    if occ.kind == "terrain":  # one height per column, layers broadcast over y
        t = occ.terrain
        h = terrain_height(*terrain_columns(spec, dtype=dtype, device=device)) if height is None else height
        h = h.reshape(shape[0], 1, shape[2])
        y = torch.arange(lo[1], hi[1], device=device).to(dtype).reshape(1, -1, 1)
        grass, dirt, stone = t.materials
        m = torch.where(y > h, 0, torch.where(y > h - 1.0, grass, torch.where(y > h - 1.0 - t.dirt_depth, dirt, stone)))
        if t.ores is not None:
            ore = ore_cells(_cells(lo, hi, device), h.expand(shape).reshape(-1), t.ores).reshape(shape)
            m = torch.where(ore & (m > 0), t.ores.material, m)
        return m.to(torch.uint8)
    cells = _cells(lo, hi, device)
    out = torch.empty(cells.shape[0], dtype=torch.uint8, device=device)
    for a in range(0, cells.shape[0], batch_cells):
        c = cells[a:a + batch_cells]
        if occ.kind == "sdf":
            d = sdf.evaluate(occ.sdf.shape, cell_centres(c, spec.origin, spec.voxel_size, dtype))
            m = torch.where(d < 0, occ.sdf.material, 0)
        else:
            m = torch.as_tensor(occ.function.fn(c), device=device).reshape(-1)
        out[a:a + batch_cells] = m.to(torch.long).clamp(0, 255).to(torch.uint8)
    return out.reshape(shape)


@dataclass
class VoxelGrid:
    """The voxel grids of B scenes.

    materials (B, Z, Y, X) uint8, zero-padded; lo (B, 3) long: cell (i, j, k) of materials[b, 0, 0, 0];
    hi (B, 3) long: end of each scene's range; origin (B, 3) and voxel_size (B,) float: placement.
    `distance` (B, Z, Y, X) uint8 Chebyshev distance field (for hybrid traversal) or None.
    `flat_materials`, `flat_distance` [B·Z·Y·X]: the same grids flattened (the Dr.Jit walk's
    tables), each the tensor the 4-D one views."""

    materials: Tensor
    lo: Tensor
    hi: Tensor
    origin: Tensor
    voxel_size: Tensor
    distance: Tensor | None = None
    flat_materials: Tensor | None = None
    flat_distance: Tensor | None = None

    @classmethod
    def from_specs(cls, specs: Sequence, *, dtype, device, with_distance: bool = False) -> "VoxelGrid":
        """The grids of B voxel `specs` (one a scene) zero-padded to one (B, Z, Y, X) shape, with
        their placement in `dtype` on `device`; `with_distance`: their Chebyshev distance fields
        too."""
        terrain = [s for s in specs if s.occupancy.kind == "terrain"]  # their heights in one call
        heights = dict(zip(map(id, terrain), terrain_heights([terrain_columns(s, dtype=dtype, device=device) for s in terrain])))
        grids = [dense_materials(s, dtype=dtype, device=device, height=heights.get(id(s))) for s in specs]
        shape = [max(g.shape[a] for g in grids) for a in range(3)]
        flat = torch.zeros(len(grids) * shape[0] * shape[1] * shape[2], dtype=torch.uint8, device=device)
        mats = flat.view(len(grids), *shape)
        for b, g in enumerate(grids):
            mats[b, : g.shape[0], : g.shape[1], : g.shape[2]] = g
        ranges = [cell_range(s) for s in specs]
        lo = torch.tensor([r[0] for r in ranges], dtype=torch.long, device=device)
        hi = torch.tensor([r[1] for r in ranges], dtype=torch.long, device=device)
        origin = torch.tensor([s.origin for s in specs], dtype=dtype, device=device)
        size = torch.tensor([s.voxel_size for s in specs], dtype=dtype, device=device)
        dist = flat_dist = None
        if with_distance:
            flat_dist = torch.stack([chebyshev_distance(m > 0) for m in mats]).flatten().clone()
            dist = flat_dist.view(mats.shape)
        return cls(mats, lo, hi, origin, size, dist, flat, flat_dist)

    def _flat(self, rel: Tensor, scene: Tensor) -> Tensor:
        """Cells [N, 3] relative to their scene's `lo` -> their index [N] in the flattened (B, Z, Y, X) grids."""
        _, Z, Y, X = self.materials.shape
        return ((scene * Z + rel[:, 2]) * Y + rel[:, 1]) * X + rel[:, 0]

    def cell_index(self, cells: Tensor, scene: Tensor) -> Tensor:
        """Cells [N, 3] long inside scenes [N]'s ranges -> their index [N] in the flattened grids."""
        return self._flat(cells - take_rows(self.lo, scene), scene)

    def flat_base(self, scene: Tensor) -> tuple[Tensor, Tensor]:
        """(base [N] long, strides [2] long): cell (i, j, k) of scene[n] is at
        ``base[n] + (k·Y + j)·X + i`` of the flattened grids (`cell_index` as one sum, for kernels
        that look cells up themselves: `walk.drjit_traverse`)."""
        base, strides = self.scene_base()
        return take_rows(base, scene), strides

    def scene_base(self) -> tuple[Tensor, Tensor]:
        """`flat_base` of each scene: (base (B,) long, strides [2] long)."""
        B, _, Y, X = self.materials.shape
        scenes = torch.arange(B, device=self.lo.device)
        return self._flat(-self.lo, scenes), torch.tensor([Y, X], dtype=torch.long, device=self.lo.device)

    def index_cell(self, index: Tensor) -> tuple[Tensor, Tensor]:
        """`cell_index`'s inverse: flat indices [N] -> (cells [N, 3] long, scenes [N])."""
        _, Z, Y, X = self.materials.shape
        scene = index // (Z * Y * X)
        rel = torch.stack([index % X, index // X % Y, index // (Y * X) % Z], dim=1)
        return rel + take_rows(self.lo, scene), scene

    def _gather(self, table: Tensor, cells: Tensor, scene: Tensor, outside: int) -> Tensor:
        lo, hi = take_rows(self.lo, scene), take_rows(self.hi, scene)
        rel = cells - lo
        within = (cells >= lo) & (cells < hi)
        inside = within[:, 0] & within[:, 1] & within[:, 2]  # not .all(dim=1): 3× slower on CPU
        rel = torch.where(inside[:, None], rel, torch.zeros_like(rel))
        vals = take_rows(table.reshape(-1), self._flat(rel, scene)).to(torch.long)
        return torch.where(inside, vals, torch.full_like(vals, outside))

    def lookup(self, cells: Tensor, scene: Tensor) -> Tensor:
        """Material ids [N] long of cells [N, 3] long in scenes [N]; 0 outside a scene's range."""
        return self._gather(self.materials, cells, scene, 0)

    def empty_radius(self, cells: Tensor, scene: Tensor) -> Tensor:
        """Chebyshev distance [N] long to the nearest occupied cell (cells outside: 1, no jump)."""
        return self._gather(self.distance, cells, scene, 1)

    def to_grid(self, points: Tensor, scene: Tensor) -> Tensor:
        """World points [N, 3] -> grid coordinates [N, 3] (cell units)."""
        return (points - take_rows(self.origin, scene)) / take_rows(self.voxel_size, scene)[:, None]

    def to_world(self, g: Tensor, scene: Tensor) -> Tensor:
        """Grid coordinates `g` [n, 3] of scenes `scene` [n] -> world points [n, 3]."""
        return take_rows(self.origin, scene) + g * take_rows(self.voxel_size, scene)[:, None]

