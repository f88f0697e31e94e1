"""An explosion: an fbm-displaced sphere, animated by `time` (the seeds' variant 1 fireball).

    R(t) = radius · (1 + growth · max(time, 0))               the ball expands from time 0
    q    = (p − center) / R(t)                               the noise expands with it
    n    = fbm(frequency · q + offset − drift · time)        value noise in [0, 1], seeded
    density = clamp(sharpness · (1 − |q| + displacement · (n − 0.5)), 0, 1)

The density is 1 in the core, falls off towards the displaced surface |q| ≈ 1 + displacement ·
(n − 0.5), and is 0 beyond it; `drift` scrolls the noise through the ball, so flames churn over
time. Density never exceeds 1, so `sigma_t` is the core's extinction (and the seeds' colour map
reads the density as a fraction, `volume.emission`).
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Annotated

import torch
from pydantic import Field
from torch import Tensor

from ..noise import lattice as noise
from ..noise.fast import fbm_sum
from ..ops import lanes
from ..schema.batch import Stacked, take
from ..schema.models import EACH, Strict, Vec3
from .fbm import Hash, noise_basis, seeded_fbm, whole_fbm


class ExplosionDensity(Strict):
    """An fbm-displaced sphere: clamp(sharpness · (1 − |q| + displacement · (fbm(frequency · q +
    offset − drift · time) − 0.5)), 0, 1), q = (p − center) / (radius · (1 + growth · max(time, 0)))."""

    center: Vec3 = (0.0, 0.0, 0.0)
    radius: float = Field(1.0, gt=0.0, le=1e6)
    growth: float = Field(0.0, ge=0.0)  # the radius grows by this fraction of itself per second from time 0
    displacement: float = Field(0.6, ge=0.0)  # how far the noise moves the surface, in radii
    sharpness: float = Field(2.5, gt=0.0)  # density gradient across the surface (1: a linear ramp to the centre)
    octaves: int = Field(5, ge=1, le=12)
    frequency: float = Field(2.5, gt=0.0, le=1e6)  # noise cells per radius
    seed: Annotated[int, EACH] = 0
    offset: Vec3 = (0.0, 0.0, 0.0)
    drift: Vec3 = (0.0, 0.6, 0.0)  # noise units per second; +y: flames rise through the ball
    hash: Hash = "table"  # its value noise's lattice hash, as `density.fbm.hash`


class ExplosionField:
    def __init__(self, params: Stacked, times: Tensor):
        self.p = params
        self.size = params.radius * (1.0 + params.growth * times.clamp_min(0.0))  # (B,) R(t)
        self.shift = params.offset - params.drift * times[:, None]  # (B, 3)
        # the finest octave's lattice period, in world units (R(t) / frequency per noise cell)
        self.feature_size = noise.finest_period(params.octaves) * self.size / params.frequency

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        return self.signed(points, scene_index, lod).clamp_min(0.0)

    def signed(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        """`points` [N, 3], `scene_index` [N], `lod` [N] octaves to drop -> [N], at most 1."""
        p, s = self.p, scene_index
        q = (points - take(p.center, s)) / take(self.size, s)[:, None]
        x = take(p.frequency, s)[:, None] * q + take(self.shift, s)
        n = seeded_fbm(noise.value_noise, x, s, p, lod, whole=whole_fbm(p.hash))
        return fireball(q.unbind(1), n, take(p.displacement, s), take(p.sharpness, s))


def fireball(q, n, displacement, sharpness):
    """clamp(sharpness · (1 − |q| + displacement · (n − 0.5)), ·, 1): the ball at `q` (three lanes,
    in radii) displaced by its noise `n`, in lanes (`ops.lanes`)."""
    return lanes.clamp_max(sharpness * (1.0 - lanes.length3(*q) + displacement * (n - 0.5)), 1.0)


def explosion_lanes(field: ExplosionField, to) -> SimpleNamespace:
    """What the explosion takes per lane (`to.per_lane`: per scene -> lanes), its noise basis and
    octave scales (`fields.fbm.noise_basis`, `to.number`)."""
    p = field.p
    q = SimpleNamespace(center=to.per_lane(p.center), size=to.per_lane(field.size), frequency=to.per_lane(p.frequency),
                        shift=to.per_lane(field.shift), displacement=to.per_lane(p.displacement),
                        sharpness=to.per_lane(p.sharpness), octaves=int(p.octaves),
                        basis=noise_basis("value", p.seed, p.hash, to))
    q.scales = [to.number(c) for c in noise.folded_scales(q.octaves, dtype=torch.float32, device="cpu")]
    return q


def explosion_density(q, p, count):
    """The explosion's signed density in lanes at p (three lanes), `count` octaves kept or None."""
    r = [(p[c] - q.center[c]) / q.size for c in range(3)]
    n = fbm_sum(q.basis, *(q.frequency * r[c] + q.shift[c] for c in range(3)), q.scales, count, q.octaves, 0.5)
    return fireball(r, n, q.displacement, q.sharpness)
