"""Particles + volume (seed 000, "Particle System + Volume"): K moving spheres, each carrying its own
noise density, in one medium. Particle k (drawn from `seed`) has a centre c_k uniform in the region,
a radius r_k uniform in `radius`, a unit direction v_k and a noise offset o_k; at `time` t it sits at

    c_k(t) = c_k + (wind + speed · v_k) · t,   u = (p − c_k(t)) / r_k   (its local frame)
    d_k(p) = max(core + amplitude · fbm(frequency · u + o_k), 0) · (1 − smoothstep(1 − edge, 1, |u|))

and the medium is Σ_k d_k (or max_k with `combine = "max"`). The falloff reaches 0 at the sphere
with zero slope, so no sphere's edge shows. Points are tested against all K centres at once ([N, K]
distances, `torch.cdist`); noise is evaluated only on the (point, particle) pairs inside a sphere.
"""

from __future__ import annotations

import functools
from types import SimpleNamespace
from typing import Annotated, Literal

import torch
from pydantic import Field, field_validator, model_validator
from torch import Tensor

from ..noise import fast as fastnoise
from ..noise import lattice as noise
from ..ops import lanes
from ..schema.batch import Stacked, per_scene, take
from ..schema.models import EACH, Strict, Vec3
from .fbm import NOISES, Hash, noise_basis, seeded_fbm, value_noise_hash, whole_fbm

MAX_PARTICLES = 256


class ParticlesDensity(Strict):
    """`count` noisy spheres drawn from `seed` inside [region_min, region_max], radii in `radius`,
    moving at `wind` + `speed` · (a random unit direction each) per second of `time`; each holds
    max(core + amplitude · fbm(frequency · local + own offset), 0) faded to 0 over its outer `edge`
    (a fraction of its radius); `combine` sums the particles or takes their maximum."""

    count: int = Field(16, ge=1, le=MAX_PARTICLES)
    seed: Annotated[int, EACH] = 0
    region_min: Vec3 = (-1.0, -1.0, -1.0)
    region_max: Vec3 = (1.0, 1.0, 1.0)
    radius: tuple[float, float] = (0.2, 0.4)
    speed: float = Field(0.0, ge=0.0)
    wind: Vec3 = (0.0, 0.0, 0.0)
    core: float = 1.0
    amplitude: float = 1.0
    frequency: float = Field(2.0, gt=0.0, le=1e6)
    octaves: int = Field(4, ge=1, le=12)
    noise: Literal["value", "perlin", "worley"] = "value"
    hash: Hash = "table"  # value noise's lattice hash, as `density.fbm.hash`
    edge: float = Field(0.5, gt=0.0, le=1.0)
    combine: Literal["sum", "max"] = "sum"

    @field_validator("radius")
    @classmethod
    def _radius(cls, v):
        if not 0.0 < v[0] <= v[1]:
            raise ValueError("radius must be (min, max) with 0 < min <= max")
        return v

    @model_validator(mode="after")
    def _hash_of_value_noise(self):
        return value_noise_hash(self)

    @model_validator(mode="after")
    def _region(self):
        if any(hi < lo for lo, hi in zip(self.region_min, self.region_max)):
            raise ValueError(f"region_max {self.region_max} must not be below region_min {self.region_min} on any axis")
        return self


def particle_draws(seed: int, count: int, dtype: torch.dtype = torch.float64) -> dict[str, Tensor]:
    """The unit draws of one scene's particles, from its seed alone (so changing a region, radius or
    speed moves the same particles): `position` [K, 3] and `size` [K] in [0, 1), `direction` [K, 3]
    unit, `offset` [K, 3] noise offsets in [0, 100)."""
    g = torch.Generator().manual_seed(int(seed) % 2**63)
    position = torch.rand(count, 3, generator=g, dtype=torch.float64)
    size = torch.rand(count, generator=g, dtype=torch.float64)
    direction = torch.randn(count, 3, generator=g, dtype=torch.float64)
    direction = direction / direction.norm(dim=1, keepdim=True).clamp_min(1e-12)
    offset = 100.0 * torch.rand(count, 3, generator=g, dtype=torch.float64)
    draws = {"position": position, "size": size, "direction": direction, "offset": offset}
    return {k: v.to(dtype) for k, v in draws.items()}


def falloff(r, edge):
    """1 − smoothstep(1 − edge, 1, r): 1 inside the core, 0 from the sphere (r = 1) on, C¹ between.
    `r` radii in units of the particle's radius, `edge` in (0, 1]; lanes (`ops.lanes`)."""
    t = lanes.clamp((r - (1.0 - edge)) / edge, 0.0, 1.0)
    return 1.0 - t * t * (3.0 - 2.0 * t)


def particle_value(f, r, core, amplitude, edge):
    """One particle's signed term (core + amplitude · f) · falloff(r), its fbm `f` at the point,
    lanes (`ops.lanes`)."""
    return (core + amplitude * f) * falloff(r, edge)


class ParticleField:
    def __init__(self, params: Stacked, times: Tensor):
        self.p = params
        self.basis = NOISES[params.noise]
        dtype, device = times.dtype, times.device
        draws = [particle_draws(seed, params.count, dtype) for seed in params.seed]
        d = {k: torch.stack([x[k] for x in draws]).to(device) for k in draws[0]}  # (B, K, ...)
        lo, hi = params.region_min[:, None], params.region_max[:, None]  # (B, 1, 3)
        velocity = params.wind[:, None] + params.speed[:, None, None] * d["direction"]
        self.centers = lo + (hi - lo) * d["position"] + velocity * times[:, None, None]  # (B, K, 3)
        r0, r1 = params.radius[:, :1], params.radius[:, 1:]
        self.radii = r0 + (r1 - r0) * d["size"]  # (B, K)
        self.offsets = d["offset"]  # (B, K, 3)
        # the smallest particle's finest octave, in world units
        self.feature_size = noise.finest_period(params.octaves) / params.frequency * params.radius[:, 0]

    @functools.cached_property
    def cells(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """`particle_cells` of the render's particles, made once: every kernel over this field
        (the march, each shadow and sky crossing) takes the same lists."""
        return particle_cells(self.centers, self.radii)

    def aabb(self) -> tuple[Tensor, Tensor]:
        """The box of the union of the spheres at the render's time: (min (B, 3), max (B, 3)); the
        density is 0 outside it."""
        r = self.radii[..., None]
        return (self.centers - r).amin(dim=1), (self.centers + r).amax(dim=1)

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        return self._evaluate(points, scene_index, lod)[0]

    def signed(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        """The density where positive; elsewhere the largest particle's signed value: its noise
        term times the falloff inside a sphere (≤ 0 there), −(|u| − 1) radii outside all."""
        density, nearest = self._evaluate(points, scene_index, lod, signed=True)
        return torch.where(density > 0, density, nearest)

    def _evaluate(self, points: Tensor, scene_index: Tensor, lod: Tensor | None, *, signed: bool = False):
        """`points` [N, 3], `scene_index` [N] -> (density [N], signed value of the nearest particle
        [N] or None)."""
        p, s = self.p, scene_index
        # distances to every centre without an [N, K, 3] temporary (cdist's direct kernel, not the
        # matmul form that cancels), then local coordinates only for the pairs inside a sphere
        dist = per_scene(points, s, len(p), lambda b, idx, x: torch.cdist(
            x, self.centers[b], compute_mode="donot_use_mm_for_euclid_dist"))  # [N, K]
        r = dist / take(self.radii, s)
        pairs = (r < 1.0).nonzero()  # the (point, particle) pairs inside a sphere, point-major
        i, k = pairs[:, 0], pairs[:, 1]
        si = s[i]
        local = (points[i] - self.centers[si, k]) / self.radii[si, k][:, None]
        q = take(p.frequency, si)[:, None] * local + self.offsets[si, k]
        f = (seeded_fbm(self.basis, q, si, p, None if lod is None else lod[i], whole=whole_fbm(p.hash)) if pairs.shape[0]
             else q.new_zeros(0))
        raw = particle_value(f, r[i, k], take(p.core, si), take(p.amplitude, si), take(p.edge, si))
        # dense [N, K] then a reduction along K: a point's sum has the same rounding in any batch
        parts = r.new_zeros(r.shape)
        parts[i, k] = raw.clamp_min(0.0)
        density = parts.sum(dim=1) if p.combine == "sum" else parts.amax(dim=1)
        if not signed:
            return density, None
        nearest = -(r - 1.0)
        nearest[i, k] = raw
        return density, nearest.amax(dim=1)


# cells along each axis of a scene's particle box, each listing the particles that reach into it:
# a point's loop runs over its cell's particles, not all of them (`particle_cells`)
CELLS = 8


def particle_cells(centers: Tensor, radii: Tensor, *, cells: int = CELLS) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Each scene's particle box (the spheres' union's) cut into cells³ cells, and per cell the
    particles whose sphere reaches into it: centers (B, K, 3), radii (B, K) -> (low (B, 3), cells
    per unit length (B, 3), first [B·cells³ + 1] (cell c's particles are rows first[c] to
    first[c + 1] of the list), the list of rows b·K + k, ascending in k within a cell). A sphere
    counts for a cell it passes within a thousandth of its radius and of a cell (and float32's
    rounding where the box lies far from the origin) of, so a point the float32 lookup puts in a
    neighbouring cell still finds every particle that holds it."""
    c, r = centers.to(torch.float64), radii.to(torch.float64)
    low, high = (c - r[..., None]).amin(dim=1), (c + r[..., None]).amax(dim=1)  # (B, 3)
    size = (high - low) / cells
    steps = torch.arange(cells, dtype=torch.float64)
    z, y, x = torch.meshgrid(steps, steps, steps, indexing="ij")
    corner = low[:, None] + torch.stack([x, y, z], dim=-1).reshape(1, -1, 3) * size[:, None]  # (B, C, 3): x fastest
    # a thousandth of a cell, and float32's rounding of a point far from the origin (16 ulps)
    slack = (1e-3 * size + 1e-6 * torch.maximum(low.abs(), high.abs()))[:, None, None]
    lo, hi = corner[:, :, None] - slack, corner[:, :, None] + size[:, None, None] + slack
    gap = (lo - c[:, None]).clamp_min(0.0) + (c[:, None] - hi).clamp_min(0.0)  # (B, C, K, 3): to the cell's box
    reach = gap.square().sum(-1) <= (r[:, None] * 1.001).square()  # (B, C, K)
    first = torch.cat([reach.new_zeros(1, dtype=torch.long), reach.sum(-1).flatten().cumsum(0)])
    b, _, k = reach.nonzero(as_tuple=True)  # (b, cell, k) ascending: each cell's particles in order
    return low, cells / (high - low), first, b * centers.shape[1] + k


def particles_lanes(field: ParticleField, to) -> SimpleNamespace:
    """What the particles take per lane (`to`: as `fields.DENSITIES`' ``lanes`` inputs): each
    scene's particles as flat tables, their cells' lists (`particle_cells`) and the lane's first
    cell, the noise and falloff."""
    p = field.p
    low, per_unit, first, rows = field.cells
    q = SimpleNamespace(combine=p.combine, octaves=int(p.octaves), low=to.per_lane(low), per_unit=to.per_lane(per_unit),
                        cell_base=to.ints(to.scene * CELLS**3), first=to.ints(first), rows=to.ints(rows),
                        centers=to.floats(field.centers.reshape(-1)), radii=to.floats(field.radii.reshape(-1)),
                        offsets=to.floats(field.offsets.reshape(-1)), frequency=to.per_lane(p.frequency),
                        core=to.per_lane(p.core), amplitude=to.per_lane(p.amplitude), edge=to.per_lane(p.edge),
                        basis=noise_basis(p.noise, p.seed, p.hash, to))
    q.scales = [to.number(c) for c in noise.folded_scales(q.octaves, dtype=torch.float32, device="cpu")]
    return q


def particles_density(q, p, count):
    """The particles' density at p (three Dr.Jit lanes), `count` octaves kept or None: a loop over
    the particles of p's cell (`particle_cells`; any other's term is 0 at p, and a sum or largest
    value skipping zeros is bitwise the one over all), each one's fbm evaluated only where p is
    inside it, summed (or the largest) in particle order. Dr.Jit only (the eager field evaluates
    the pairs inside a sphere at once); the per-pair term is `particle_value`, the same function
    eager calls."""
    import drjit as dr
    from drjit.llvm import Float

    width = dr.width(p[0])
    unit = [(p[a] - q.low[a]) * q.per_unit[a] for a in range(3)]
    # far points clamped to the border cells (no particle holds them), NaN to cell 0 (r is NaN: 0)
    cell = [lanes.to_int32(lanes.floor(lanes.clamp(lanes.where(u == u, u, 0.0), 0.0, CELLS - 1.0))) for u in unit]
    at = q.cell_base + (cell[2] * CELLS + cell[1]) * CELLS + cell[0]
    start, stop = lanes.gather(q.first, at), lanes.gather(q.first, at + 1)

    def body(j, total):
        i = lanes.gather(q.rows, j)
        v = [p[a] - lanes.gather(q.centers, i * 3 + a) for a in range(3)]
        radius = lanes.gather(q.radii, i)
        r = lanes.length3(*v) / radius

        def inside():
            u = [q.frequency * (v[a] / radius) + lanes.gather(q.offsets, i * 3 + a) for a in range(3)]
            f = fastnoise.fbm_sum(q.basis, *u, q.scales, count, q.octaves, 0.5)
            return lanes.clamp_min(particle_value(f, r, q.core, q.amplitude, q.edge), 0.0)

        part = dr.if_stmt((), r < 1.0, inside, lambda: dr.zeros(Float, width))
        return j + 1, total + part if q.combine == "sum" else lanes.maximum(total, part)

    return dr.while_loop((start, dr.zeros(Float, width)), lambda j, total: j < stop, body, mode="symbolic")[1]
