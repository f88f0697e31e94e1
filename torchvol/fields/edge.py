"""Density faded to 0 towards the volume's bounds, so that no bounding shape shows:
density · smoothstep(0, width, depth), `depth` the distance from the point in to the bounds'
surface (a sphere's r − |p − c|, a box's nearest face, a slab's nearest plane; the bounds kind's
`depth`), or to the plane y = `base` below it where given (height shaping: a cumulus' flat base).
Wraps any field; the fade is applied wherever the density is read (view march, shadow and ambient
rays, sun grids)."""

from __future__ import annotations

import torch
from pydantic import Field
from torch import Tensor

from ..ops import lanes
from ..schema.batch import Stacked, take
from ..schema.models import Strict


class Edge(Strict):
    """`volumes[i].edge`: density · smoothstep(0, width, distance inside the bounds)."""

    width: float = Field(0.3, gt=0.0, description="world units over which the density fades in from the bounds")
    base: float | None = Field(None, description="world height of a flat base: no density below it, fading in over width")


def faded(density, depth, width):
    """`density` · smoothstep(0, `width`, `depth`), in lanes (`ops.lanes`): the edge's fade of a
    density at `depth` inside the bounds."""
    return density * lanes.smoothstep01(depth / width)


class EdgeField:
    """`inner` (a density field of B scenes) faded towards the bounds: `depth(bounds, p [n, 3], s [n])
    -> [n]` the bounds kind's distance inside, `edge` the batch's `Edge` tables. Other attributes are the inner field's
    (a grid's occupancy stays a superset of the faded one's, so empty-space skipping holds)."""

    def __init__(self, inner, depth, bounds: Stacked, edge: Stacked):
        self.inner, self.depth, self.bounds, self.edge = inner, depth, bounds, edge
        self.feature_size = inner.feature_size

    def fade(self, points: Tensor, s: Tensor) -> Tensor:
        """The fade towards the bounds (and the base, where the edge has one) at `points` [n, 3] of
        scenes `s` [n]: [n] in [0, 1]."""
        depth = self.depth(self.bounds, points, s)
        if self.edge.base is not None:
            depth = torch.minimum(depth, points[:, 1] - take(self.edge.base, s))
        return faded(1.0, depth, take(self.edge.width, s))

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        return self.inner(points, scene_index, lod) * self.fade(points, scene_index)

    def signed(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        """The inner field's signed density [n] at `points` [n, 3] of scenes `scene_index` [n]
        (`lod` [n] or None), faded where it is positive."""
        raw = self.inner.signed(points, scene_index, lod)
        return raw.where(raw <= 0.0, raw * self.fade(points, scene_index))  # empty stays as far from density

    def __getattr__(self, name: str):
        if name == "inner":  # not set yet (a copy under construction): no recursion
            raise AttributeError(name)
        return getattr(self.inner, name)
