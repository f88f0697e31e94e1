"""Emission colour maps and the seeds' bloom glow, as source terms of the physical medium.

`EMISSION_MAPS` (`volumes[i].emission_map = { explosion = {...} }`): a kind's function
`fn(params (Stacked), points [n, 3], density [n], s [n]) -> σe [n, 3]`, the emitted radiance per
unit length at the samples. The one kind, ``explosion``, is the seeds' variant 1 `computeColor`:

    colour(ρ, r) = mix(thin, dense, min(ρ, 1)) · mix(core, edge, min(r / reach, overshoot))
    σe = scale · max(colour(ρ, |p − center| / radius), 0) · ρ

Emission is radiance per unit length, proportional to the density of what glows (hot soot: twice
the particles emit twice the light), so σe carries the factor ρ, exactly as the constant
`emission` does; the colour map is its spectrum, a temperature proxy (white-hot core, dim red
edges). A thick region saturates to L = σe / σt = scale · colour / sigma_t, like a black body's
surface. The seeds' ramp overshoots `edge` (min(r / 0.9, 1.15) > 1) and goes slightly negative
beyond r ≈ 1: emission is clamped at 0 there (no negative light), which fades the ball's rim out.
The density mix is clamped at ρ = 1 for the same reason (a density over 1 would extrapolate).

`Bloom` (`volumes[i].bloom = { light = 0, ... }`): the seeds' in-loop glow around their point
light, `sum.rgb += lightColor / exp(d³ · 0.08) / 30` on every step, whatever the density. It is
an artistic term, not light transport: it makes the light's surroundings glow as if the medium
were lit everywhere. Here it is a source per unit length, strength · intensity · color ·
e^{−falloff · d³} (d the distance to the light), added where the volume is marched; per unit
length instead of per step, so the image does not change with the step count (the default
strength 1/30 per step ÷ the seeds' step 0.05 = 2/3 matches their look), and seen through the
medium in front of it, like emission.
"""

from __future__ import annotations

from types import SimpleNamespace

import torch
from pydantic import Field, field_validator
from torch import Tensor

from ..light.lights import radiant
from ..ops import lanes
from ..schema.batch import Stacked, take
from ..schema.models import Strict, Vec3, nonneg
from ..schema.registry import Registry

SEED_STEP = 0.05  # the seeds' STEP_SIZE: their glow is 1/30 per step of this length


class ExplosionMap(Strict):
    """The seeds' `computeColor(density, radius)` as emitted radiance per unit length:
    scale · max(mix(thin, dense, min(ρ, 1)) · mix(core, edge, min(r / reach, overshoot)), 0) · ρ,
    r = |p − center| / radius."""

    center: Vec3 = (0.0, 0.0, 0.0)
    radius: float = Field(1.0, gt=0.0, le=1e6)  # the world distance the ramp reads as radius 1
    scale: float = Field(1.0, ge=0.0)  # radiance per unit length at density 1, per unit of colour
    thin: Vec3 = (1.0, 0.9, 0.8)  # colour at density 0
    dense: Vec3 = (0.4, 0.15, 0.1)  # colour at density 1
    core: Vec3 = (5.6, 7.0, 7.0)  # 7 · (0.8, 1, 1): the ramp at the centre (HDR)
    edge: Vec3 = (0.72, 0.795, 0.75)  # 1.5 · (0.48, 0.53, 0.5): the ramp at r = reach
    reach: float = Field(0.9, gt=0.0)
    overshoot: float = Field(1.15, ge=0.0)  # the ramp's parameter is capped here (past `edge` when > 1)

    _c = field_validator("thin", "dense", "core", "edge")(lambda v: nonneg(v))


class Bloom(Strict):
    """The seeds' glow around a point light (artistic): strength · intensity · color ·
    e^{−falloff · d³} per unit length, d the distance to point light `lights[light]`."""

    light: int = Field(0, ge=0)
    strength: float = Field(1.0 / 30.0 / SEED_STEP, ge=0.0)
    falloff: float = Field(0.08, ge=0.0)


def mix(a, b, w):
    """GLSL mix(a, b, w) = a · (1 − w) + b · w, lanes (`ops.lanes`)."""
    return a * (1.0 - w) + b * w


def explosion_lanes(params: Stacked, to) -> SimpleNamespace:
    """The colour map's parameters per lane (`to.per_lane`: per scene -> lanes; colours three lanes)."""
    return SimpleNamespace(**{name: to.per_lane(getattr(params, name)) for name in ExplosionMap.model_fields})


def explosion_glow(q, p, density):
    """σe, three lanes (`ops.lanes`), at p (three lanes) of density `density` (≥ 0): scale ·
    max(mix(thin, dense, min(ρ, 1)) · mix(core, edge, min(r / reach, overshoot)), 0) · ρ, r = |p −
    center| / radius; `q` from `explosion_lanes`."""
    c = q.center
    r = lanes.length3(p[0] - c[0], p[1] - c[1], p[2] - c[2]) / q.radius
    color = _color(lanes.clamp_max(density, 1.0), r, q.thin, q.dense, q.core, q.edge, q.reach, q.overshoot)
    weight = q.scale * density
    return [lanes.clamp_min(c, 0.0) * weight for c in color]


def _color(density, radius, thin, dense, core, edge, reach, overshoot) -> list:
    """The seeds' computeColor, unclamped, in lanes: colours three lanes each -> three lanes."""
    t = lanes.minimum(radius / reach, overshoot)
    return [mix(thin[i], dense[i], density) * mix(core[i], edge[i], t) for i in range(3)]


def explosion_color(density: Tensor, radius: Tensor, *, thin: Tensor, dense: Tensor, core: Tensor, edge: Tensor,
                    reach: Tensor, overshoot: Tensor) -> Tensor:
    """The seeds' computeColor, unclamped: `density`, `radius` [n]; colours [n, 3]; `reach`,
    `overshoot` [n] -> [n, 3]."""
    return torch.stack(_color(density, radius, thin.unbind(-1), dense.unbind(-1), core.unbind(-1), edge.unbind(-1), reach,
                              overshoot), dim=-1)


def explosion_emission(params: Stacked, points: Tensor, density: Tensor, s: Tensor) -> Tensor:
    """σe [n, 3] at `points` [n, 3] of density `density` [n] (≥ 0) in scenes `s` [n]."""
    q = explosion_lanes(params, SimpleNamespace(per_lane=lambda v: lanes.columns(take(v, s))))
    return torch.stack(explosion_glow(q, points.unbind(1), density), dim=1)


def bloom_lanes(bloom: Stacked, light: Stacked, to) -> SimpleNamespace:
    """The glow's and its point light's parameters per lane (`to.per_lane`)."""
    return SimpleNamespace(strength=to.per_lane(bloom.strength), falloff=to.per_lane(bloom.falloff),
                           position=to.per_lane(light.position), radiant=to.per_lane(radiant(light)))


def bloom_source(q, p):
    """The glow, three lanes, at p (three lanes): strength · intensity · color · e^{−falloff · d³};
    `q` from `bloom_lanes`."""
    v = [p[c] - q.position[c] for c in range(3)]
    d2 = lanes.dot3(v, v)
    weight = q.strength * lanes.exp(-q.falloff * d2 * lanes.sqrt(d2))
    return [e * weight for e in q.radiant]


def bloom_glow(bloom: Stacked, light: Stacked, points: Tensor, s: Tensor) -> Tensor:
    """The glow source [n, 3] at `points` [n, 3] of scenes `s` [n] around point light `light`
    (its `Stacked` parameters: position, color, intensity)."""
    q = bloom_lanes(bloom, light, SimpleNamespace(per_lane=lambda v: lanes.columns(take(v, s))))
    return torch.stack(bloom_source(q, points.unbind(1)), dim=1)



EMISSION_MAPS = Registry("emission map")
# `lanes = (inputs(params, to), glow(q, p, density))`: the map in lanes, what the Dr.Jit march traces
EMISSION_MAPS.register("explosion", ExplosionMap, explosion_emission, lanes=(explosion_lanes, explosion_glow))
EmissionMap = EMISSION_MAPS.one_of("EmissionMap", "An emission colour map: `{ explosion = {...} }`.")
