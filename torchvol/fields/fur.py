"""A fur ball (the seeds' variant 5): a dense core of radius `radius` with radial strands out to
`radius + length`. A strand is a direction on the sphere: Worley noise at `frequency` · (unit
direction) depends on the direction only, so it is constant along radial lines; a strand is where
it is under `thickness`, tapering to nothing at the tips.

density = scale · clamp(max(core, strand), 0, 1), core = (radius − r) / length,
strand = taper − F1(frequency · u) / thickness, taper = (radius + length − r) / length (≤ 1),
with r = |p − center| and u = (p − center) / r."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Annotated

from pydantic import Field
from torch import Tensor

from ..noise import lattice as noise
from ..ops import lanes
from ..schema.batch import Stacked, take
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
    def __init__(self, params: Stacked, times: Tensor):
        self.p = params
        # a strand's width at its tip, in world units (the finest detail)
        self.feature_size = params.thickness / params.frequency * (params.radius + params.length)

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        return take(self.p.scale, scene_index) * self.unscaled(points, scene_index).clamp(0.0, 1.0)

    def signed(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        """scale · max(core, strand) before the clamp, `points` [N, 3] -> [N] (`lod` does not apply)."""
        return take(self.p.scale, scene_index) * self.unscaled(points, scene_index)

    def unscaled(self, points: Tensor, scene_index: Tensor) -> Tensor:
        """max(core, strand), `points` [N, 3] -> [N] (`fur_unscaled` on torch columns)."""
        p, s = self.p, scene_index
        perm, values = noise.scene_lattice_tables(tuple(int(x) for x in p.seed), str(points.device))
        rows = noise.scene_rows(s)
        points_of = [noise.chained_values(perm, v.to(points.dtype)) for v in values]
        worley = lambda q: noise.worley_lanes(*q, perm, points_of, rows)  # noqa: E731
        q = SimpleNamespace(**{k: lanes.columns(take(getattr(p, k), s)) for k in ("center", "radius", "length", "frequency",
                                                                                  "thickness")})
        return fur_unscaled(q, points.unbind(1), worley)


def fur_unscaled(q: SimpleNamespace, p, worley):
    """max(core, strand) at p (three lanes), `ops.lanes`: `q` the ball's parameters per lane
    (center: three lanes; radius, length, frequency, thickness), `worley(three lanes)` its F1."""
    rel = [p[c] - q.center[c] for c in range(3)]
    r = lanes.length3(*rel)
    inv = lanes.clamp_min(r, 1e-12)  # the centre itself: u = 0, inside the core anyway
    f1 = worley([q.frequency * (rel[c] / inv) for c in range(3)])
    core = (q.radius - r) / q.length
    strand = lanes.clamp_max((q.radius + q.length - r) / q.length, 1.0) - f1 / q.thickness
    return lanes.maximum(core, strand)


def fur_lanes(field: FurField, to) -> SimpleNamespace:
    """What the fur takes per lane (`to`: `fields.DENSITIES`' ``lanes`` inputs)."""
    p = field.p
    q = SimpleNamespace(**{k: to.per_lane(getattr(p, k)) for k in ("center", "radius", "length", "frequency", "thickness",
                                                                    "scale")})
    perm, values = noise.scene_lattice_tables(tuple(int(x) for x in p.seed), "cpu")
    q.perm, q.rows = to.ints(perm), to.ints(noise.scene_rows(to.scene))
    q.values = [to.floats(noise.chained_values(perm, v)) for v in values]
    return q


def fur_density(q, p, count):
    """The fur's density at p (three lanes): scale · clamp(max(core, strand), 0, 1), as the field
    reads it (`count` does not apply)."""
    worley = lambda u: noise.worley_lanes(*u, q.perm, q.values, q.rows)  # noqa: E731
    return q.scale * lanes.clamp(fur_unscaled(q, p, worley), 0.0, 1.0)
