"""Skies: the `SKIES` registry. Each kind is its schema model (the `[sky]` table, chosen by its
``kind`` key) and its function `fn(sky (Stacked), directions [n, 3], scene_index [n], sun (B, 3)
| None) -> radiance [n, 3]` (`sun`: the unit direction towards the first light, a sun, where the
scene has one). Every sky may add the sun's glow lobes: `halo` (seen through volumes) and `flare`
(added over everything after compositing)."""

from __future__ import annotations

from typing import Literal

import torch
from pydantic import Field, field_validator, model_validator
from torch import Tensor

from ..geometry.rays import intersect_sphere
from ..ops import lanes
from ..ops.mathops import pow_
from ..runtime.compilation import traced_vectors
from ..schema.batch import Stacked, take
from ..schema.models import Strict, Vec3, nonneg
from ..schema.registry import Registry
from .atmosphere import Air, AirLayer, gather_air, single_scatter, single_scatter_kernel


class Glow(Strict):
    """An additive lobe around the sun: color · clamp(dot(sun, rd), 0, 1)^power."""

    color: Vec3
    power: float = Field(gt=0.0)
    _c = field_validator("color")(lambda v: nonneg(v))


class Atmosphere(AirLayer):
    """The sky of a spherical planet's air seen from `eye_height` above its ground (the defaults are
    Earth's in metres); the sun is the scene's first light, of radiance scale `sun_intensity`."""

    eye_height: float = Field(1.0, ge=0.0)
    sun_intensity: float = Field(20.0, ge=0.0)

    @model_validator(mode="after")
    def _eye_inside(self):
        if self.eye_height >= self.atmosphere_height:
            raise ValueError("eye_height must be below atmosphere_height")
        return self


class SkyBase(Strict):
    halo: Glow | None = None  # added to the sky (seen through volumes)
    flare: Glow | None = None  # added over everything, after compositing


class ConstantSky(SkyBase):
    kind: Literal["constant"] = "constant"
    radiance: Vec3 = (0.0, 0.0, 0.0)
    _r = field_validator("radiance")(lambda v: nonneg(v))


class GradientSky(SkyBase):
    """The template's sky: colour = horizon − rd.y · slope."""

    kind: Literal["gradient"] = "gradient"
    horizon: Vec3 = (0.675, 0.785, 0.825)  # colour at rd.y = 0
    slope: Vec3 = (0.2, 0.1, 0.2)


class AtmosphereSky(SkyBase):
    kind: Literal["atmosphere"] = "atmosphere"
    atmosphere: Atmosphere = Field(default_factory=Atmosphere)


def gradient_sky(directions: Tensor, horizon: Tensor, slope: Tensor) -> Tensor:
    """The template's `bgcol = horizon − rd.y · slope`, never below 0 (a radiance; a steep slope
    would take it there). `directions`: [R, 3]; `horizon`, `slope`: [R, 3] (gathered per ray). -> [R, 3]."""
    return torch.stack(gradient_lanes(directions.unbind(1), horizon.unbind(1), slope.unbind(1)), dim=1)


def gradient_lanes(d: list, horizon: list, slope: list) -> list:
    """`gradient_sky` in lanes (`ops.lanes`): three lanes each -> three."""
    return [lanes.clamp_min(horizon[c] - d[1] * slope[c], 0.0) for c in range(3)]


def sun_glow(directions: Tensor, sun_dir: Tensor, color: Tensor, power: Tensor) -> Tensor:
    """color · clamp(dot(sun, rd), 0, 1)^power: the template's halo (power 8) and flare (power 3).
    `directions`, `sun_dir`, `color`: [R, 3]; `power`: [R]. -> [R, 3]."""
    return torch.stack(glow_lanes(directions.unbind(1), sun_dir.unbind(1), color.unbind(1), power), dim=1)


def glow_lanes(d: list, sun_dir: list, color: list, power) -> list:
    """`sun_glow` in lanes (`ops.lanes`): three lanes each, `power` one -> three."""
    glow = pow_(lanes.clamp(lanes.dot3(d, sun_dir), 0.0, 1.0), power)
    return [color[c] * glow for c in range(3)]


def atmosphere_sky(directions: Tensor, sun_dir: Tensor, air: Air, *, eye_height: Tensor, sun_intensity: Tensor,
                   steps: int, light_steps: int, kernel: bool = False) -> Tensor:
    """Single-scattering Rayleigh + Mie sky (seed 000, variant 2) seen from `eye_height` [R] above
    the planet of `air` (per ray): `volume.atmosphere.single_scatter` up to the top of the
    atmosphere, or to the ground (black) for rays towards it, as one Dr.Jit kernel where `kernel`
    (`single_scatter_kernel`). `directions`, `sun_dir`: [R, 3] unit (sun towards the sun);
    `sun_intensity` [R]. Returns radiance [R, 3]."""
    centre = torch.zeros_like(directions)
    origin = torch.zeros_like(directions)
    origin[:, 1] = air.planet_radius + eye_height
    _, t_top = intersect_sphere(origin, directions, centre, air.top_radius)
    g_near, _ = intersect_sphere(origin, directions, centre, air.planet_radius)
    t_end = torch.where(g_near > 0, torch.minimum(g_near, t_top), t_top).clamp_min(0.0)
    scatter = single_scatter_kernel if kernel else lambda *a, **k: single_scatter(*a, **k)[0]
    inscatter = scatter(origin, directions, torch.zeros_like(t_end), t_end, sun_dir, air, steps=steps,
                        light_steps=light_steps)
    return sun_intensity[:, None] * inscatter


def _atmosphere(sky: Stacked, directions: Tensor, s: Tensor, sun: Tensor, *, kernel: bool = False) -> Tensor:
    atm = sky.atmosphere
    return atmosphere_sky(directions, take(sun, s), gather_air(atm, s, kernel=kernel), eye_height=take(atm.eye_height, s),
                          sun_intensity=take(atm.sun_intensity, s), steps=atm.steps, light_steps=atm.light_steps,
                          kernel=kernel)


SKIES = Registry("sky")
# `kernel`: where the render runs kernels, the sky is one: with `lanes(sky, per_lane, d)` (the kind
# in lanes, its parameters per scene made lanes by `per_lane`, directions d three lanes) it and
# the halo as one (`sky_kernel`: a 256² cloudscape's sky 1.7 -> 1.1 ms on the glue's thread),
# without, the kind's fn(..., kernel=True)
SKIES.register("constant", ConstantSky, lambda sky, d, s, sun: take(sky.radiance, s), kernel=True,
               lanes=lambda sky, per_lane, d: per_lane(sky.radiance))
SKIES.register("gradient", GradientSky, lambda sky, d, s, sun: gradient_sky(d, take(sky.horizon, s), take(sky.slope, s)),
               kernel=True, lanes=lambda sky, per_lane, d: gradient_lanes(d, per_lane(sky.horizon), per_lane(sky.slope)))
SKIES.register("atmosphere", AtmosphereSky, _atmosphere, needs_sun=True, kernel=True)


def sky_kernel(kind, sky: Stacked, directions: Tensor, s: Tensor, sun: Tensor | None) -> Tensor:
    """The sky of `kind` (one with ``lanes``) seen along unit `directions` [n, 3] of scenes `s`
    [n], with the halo where `sun` (B, 3) is given, as one Dr.Jit kernel -> [n, 3]. The gradient
    bitwise eager's; the halo's power Dr.Jit's exp and log (within float rounding)."""
    per_lane = lanes.per_scene_lanes(s)

    def radiance(lane):
        d = lanes.vector_lanes(directions)
        base = kind.lanes(sky, per_lane, d)
        if sun is None:
            return base
        glow = glow_lanes(d, per_lane(sun), per_lane(sky.halo.color), per_lane(sky.halo.power))
        return [base[c] + glow[c] for c in range(3)]

    return traced_vectors(radiance, directions)
