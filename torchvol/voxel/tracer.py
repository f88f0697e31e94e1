"""World rays through a batch's voxel grids: the DDA the plan picked (the Dr.Jit walk, the
hybrid distance-field skip or the eager walk), shadow rays, and the render's count of DDA steps.
Every voxel pass traces through one `VoxelTracer`."""

from __future__ import annotations

from torch import Tensor

from ..light.lights import LightSource
from ..ops.mathops import take_rows
from .dda import Hits, hybrid_traverse, traverse
from .fog import FogWalk, GlowWalk
from .grid import VoxelGrid
from .shade import voxel_ao
from .shade_kernel import ao_kernel
from .walk import drjit_traverse, int_table

__all__ = ["VoxelTracer"]


class VoxelTracer:
    """Traces rays through `grid` (the batch's `VoxelGrid`) by `traversal` ("dda" or "hybrid",
    the plan's): every walk as one Dr.Jit kernel where `drjit` (`walk.drjit_traverse`), else
    eagerly (`dda.traverse`, `dda.hybrid_traverse`);
    `steps_total` the DDA steps counted so far."""

    def __init__(self, grid: VoxelGrid, traversal: str, drjit: bool = False):
        self.grid, self.traversal, self.drjit = grid, traversal, drjit
        self.steps_total = 0
        self._tables: dict = {}  # the grids as Dr.Jit arrays, converted on first use

    def traverse(self, o: Tensor, d: Tensor, s: Tensor, *, max_steps: int, t_min=None, t_max=None, visit=None,
                 fog: FogWalk | None = None, glow: GlowWalk | None = None, plain=False) -> Hits:
        """World rays o, d [n, 3] of scenes s [n] through their grids (t in world units); `visit`
        the eager walk's per-cell callback, `fog` and `glow` the Dr.Jit walk's sums; `plain`: no
        hybrid skip."""
        g = self.grid
        og, dg = g.to_grid(o, s), d / take_rows(g.voxel_size, s)[:, None]
        hybrid = self.traversal == "hybrid" and visit is None and fog is None and glow is None and not plain
        if self.drjit and visit is None:
            base, strides = g.scene_base()
            return drjit_traverse(og, dg, self._table("table"), base, strides, g.lo, g.hi, max_steps=max_steps,
                                  t_min=t_min, t_max=t_max, distance=self._table("distance") if hybrid else None,
                                  fog=fog, glow=glow, scene=s)
        lookup = lambda c, ids: g.lookup(c, take_rows(s, ids))
        lo, hi = take_rows(g.lo, s), take_rows(g.hi, s)
        if hybrid:
            return hybrid_traverse(og, dg, lookup, lambda c, ids: g.empty_radius(c, take_rows(s, ids)), lo, hi,
                                   max_steps=max_steps, t_min=t_min)
        return traverse(og, dg, lookup, lo, hi, max_steps=max_steps, t_min=t_min, t_max=t_max, visit=visit)

    def visibility(self, p: Tensor, s: Tensor, light: LightSource, steps: int, toward=None) -> Tensor:
        """Visibility [n] (1 lit, 0 occluded) of points p [n, 3] of scenes s [n] towards `light` (a
        shadow ray of at most `steps` cells that ends at the light; `toward` its `light.toward(p, s)`
        where the caller has it)."""
        if p.shape[0] == 0:
            return p.new_zeros(0)
        toward = light.toward(p, s) if toward is None else toward
        t_max = None if light.directional else toward.distance
        h = self.traverse(p, toward.direction, s, max_steps=steps, t_max=t_max, plain=True)
        return (~h.hit).to(p.dtype)

    def ao(self, cell: Tensor, normal: Tensor, axis: Tensor, uv: Tensor, gamma: Tensor, s: Tensor) -> Tensor:
        """`shade.voxel_ao` [n] of hits of scenes s [n] (cell [n, 3] long, face normal [n, 3], axis [n],
        uv [n, 2], gamma [n]): one Dr.Jit kernel where `drjit`, else eagerly."""
        g = self.grid
        if not self.drjit:
            return voxel_ao(lambda c: g.lookup(c, s) > 0, cell, normal, axis, uv, gamma=gamma)
        base, strides = g.scene_base()
        return ao_kernel(self._table("table"), base, strides, g.lo, g.hi, cell, normal, axis, uv, gamma, scene=s)

    def _table(self, name: str):
        """The grid's flattened materials ("table") or distances ("distance") as a Dr.Jit array,
        converted once."""
        if not self._tables:
            g = self.grid
            self._tables = {"table": int_table(g.flat_materials),
                            "distance": None if g.flat_distance is None else int_table(g.flat_distance)}
        return self._tables[name]

    def count(self, steps: Tensor) -> None:
        """Adds rays' DDA steps [n] to `steps_total` (primary, secondary and GI rays; shadow rays
        are not counted)."""
        self.steps_total += int(steps.sum())
