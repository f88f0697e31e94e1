"""A fur ball (the seeds' variant 5): a dense core of radius `radius` with radial strands out to
`radius + length`. A strand is a direction on the sphere: Worley noise at `frequency` · (unit
direction) depends on the direction only, so it is constant along radial lines; a strand is where
it is under `thickness`, tapering to nothing at the tips.

density = scale · clamp(max(core, strand), 0, 1), core = (radius − r) / length,
strand = taper − F1(frequency · u) / thickness, taper = (radius + length − r) / length (≤ 1),
with r = |p − center| and u = (p − center) / r."""

from __future__ import annotations

from typing import Annotated

import torch
from pydantic import Field
from torch import Tensor

from ..noise import lattice as noise
from ..schema.batch import Stacked, per_scene, take
from ..schema.models import EACH, Strict, Vec3


class FurDensity(Strict):
    """A core of `radius` with radial strands `length` long (strands per unit angle ~ `frequency`,
    their width at the root `thickness` in Worley units of that angular lattice)."""

    center: Vec3 = (0.0, 0.0, 0.0)
    radius: float = Field(0.6, gt=0.0)
    length: float = Field(0.35, gt=0.0)
    frequency: float = Field(24.0, gt=0.0, le=1e4)
    thickness: float = Field(0.3, gt=0.0, le=2.0)
    scale: float = Field(1.0, ge=0.0)
    seed: Annotated[int, EACH] = 0


class FurField:
    def __init__(self, params: Stacked, times: Tensor, *, compiled: bool = False):
        self.p = params
        self.worley = noise.compiled_noise(noise.worley_noise) if compiled else noise.worley_noise
        # a strand's width at its tip, in world units (the finest detail)
        self.feature_size = params.thickness / params.frequency * (params.radius + params.length)

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        return take(self.p.scale, scene_index) * self.unscaled(points, scene_index).clamp(0.0, 1.0)

    def signed(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        """scale · max(core, strand) before the clamp, `points` [N, 3] -> [N] (`lod` does not apply)."""
        return take(self.p.scale, scene_index) * self.unscaled(points, scene_index)

    def unscaled(self, points: Tensor, scene_index: Tensor) -> Tensor:
        """max(core, strand), `points` [N, 3] -> [N]."""
        p, s = self.p, scene_index
        rel = points - take(p.center, s)
        r = rel.norm(dim=1)
        u = rel / r.clamp_min(1e-12)[:, None]  # the centre itself: u = 0, inside the core anyway
        q = take(p.frequency, s)[:, None] * u
        f1 = per_scene(q, s, len(p), lambda b, idx, q_b: self.worley(q_b, seed=p.seed[b]))
        radius, length = take(p.radius, s), take(p.length, s)
        core = (radius - r) / length
        strand = ((radius + length - r) / length).clamp_max(1.0) - f1 / take(p.thickness, s)
        return torch.maximum(core, strand)
