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

from pydantic import Field, field_validator
from torch import Tensor

from ..light.lights import radiant
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


def explosion_color(density: Tensor, radius: Tensor, *, thin: Tensor, dense: Tensor, core: Tensor, edge: Tensor,
                    reach: Tensor, overshoot: Tensor) -> Tensor:
    """The seeds' computeColor, unclamped: `density`, `radius` [n]; colours [n, 3]; `reach`,
    `overshoot` [n] -> [n, 3]."""
    base = mix(thin, dense, density[:, None])
    ramp = mix(core, edge, (radius / reach).minimum(overshoot)[:, None])
    return base * ramp


def mix(a: Tensor, b: Tensor, w: Tensor) -> Tensor:
    """GLSL mix(a, b, w) = a · (1 − w) + b · w; [n, 3] with `w` [n, 1]."""
    return a * (1.0 - w) + b * w


def explosion_emission(params: Stacked, points: Tensor, density: Tensor, s: Tensor) -> Tensor:
    """σe [n, 3] at `points` [n, 3] of density `density` [n] (≥ 0) in scenes `s` [n]."""
    radius = (points - take(params.center, s)).norm(dim=1) / take(params.radius, s)
    color = explosion_color(density.clamp_max(1.0), radius, thin=take(params.thin, s), dense=take(params.dense, s),
                            core=take(params.core, s), edge=take(params.edge, s), reach=take(params.reach, s),
                            overshoot=take(params.overshoot, s))
    return color.clamp_min(0.0) * (take(params.scale, s) * density)[:, None]


def bloom_glow(bloom: Stacked, light: Stacked, points: Tensor, s: Tensor) -> Tensor:
    """The glow source [n, 3] at `points` [n, 3] of scenes `s` [n] around point light `light`
    (its `Stacked` parameters: position, color, intensity)."""
    v = points - take(light.position, s)
    d2 = (v * v).sum(dim=1)
    weight = take(bloom.strength, s) * (-take(bloom.falloff, s) * d2 * d2.sqrt()).exp()
    return take(radiant(light), s) * weight[:, None]


EMISSION_MAPS = Registry("emission map")
EMISSION_MAPS.register("explosion", ExplosionMap, explosion_emission)
EmissionMap = EMISSION_MAPS.one_of("EmissionMap", "An emission colour map: `{ explosion = {...} }`.")
