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

from .batch import Stacked, take
from .mathops import pow_
from .rays import intersect_sphere
from .registry import Registry
from .schema import Strict, Vec3, nonneg
from .volume.phase import mie_cornette_shanks, rayleigh as rayleigh_phase


class Glow(Strict):
    """An additive lobe around the sun: color · clamp(dot(sun, rd), 0, 1)^power."""

    color: Vec3
    power: float = Field(gt=0.0)
    _c = field_validator("color")(lambda v: nonneg(v))


class Atmosphere(Strict):
    """Rayleigh + Mie single scattering around a spherical planet (lengths in world units; the
    defaults are Earth's in metres). The sun is the scene's first light."""

    planet_radius: float = Field(6.36e6, gt=0.0)
    atmosphere_height: float = Field(6.0e4, gt=0.0)
    eye_height: float = Field(1.0, ge=0.0)
    rayleigh: Vec3 = (5.8e-6, 13.5e-6, 33.1e-6)
    mie: float = Field(21e-6, ge=0.0)
    rayleigh_height: float = Field(7994.0, gt=0.0)
    mie_height: float = Field(1200.0, gt=0.0)
    mie_g: float = Field(0.76, gt=-1.0, lt=1.0)
    sun_intensity: float = Field(20.0, ge=0.0)
    steps: int | None = Field(None, ge=1, le=1024, description="None: the quality level's")
    light_steps: int | None = Field(None, ge=1, le=1024, description="None: the quality level's")
    _r = field_validator("rayleigh")(lambda v: nonneg(v))

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
    """The template's `bgcol = horizon − rd.y · slope`. `directions`: [R, 3]; `horizon`, `slope`:
    [R, 3] (gathered per ray). -> [R, 3]."""
    return horizon - directions[:, 1:2] * slope


def sun_glow(directions: Tensor, sun_dir: Tensor, color: Tensor, power: Tensor) -> Tensor:
    """color · clamp(dot(sun, rd), 0, 1)^power: the template's halo (power 8) and flare (power 3).
    `directions`, `sun_dir`, `color`: [R, 3]; `power`: [R]. -> [R, 3]."""
    sun = (directions * sun_dir).sum(dim=1).clamp(0.0, 1.0)
    return color * pow_(sun, power)[:, None]


def atmosphere_sky(
    directions: Tensor,
    sun_dir: Tensor,
    *,
    planet_radius: Tensor,
    atmosphere_radius: Tensor,
    eye_height: Tensor,
    rayleigh: Tensor,
    mie: Tensor,
    rayleigh_height: Tensor,
    mie_height: Tensor,
    mie_g: Tensor,
    sun_intensity: Tensor,
    steps: int,
    light_steps: int,
) -> Tensor:
    """Single-scattering Rayleigh + Mie sky (seed 000, variant 2) seen from `eye_height` above a
    spherical planet: nested marches of exponential densities with Beer-Lambert to the sun.

    `directions`, `sun_dir`: [R, 3] unit (sun towards the sun); `rayleigh`: [R, 3] and `mie`: [R]
    scattering coefficients at sea level (per world unit); radii, heights, `mie_g`,
    `sun_intensity`: [R]. Rays towards the ground stop there (the ground itself is black).
    Returns radiance [R, 3]."""
    centre = torch.zeros_like(directions)
    origin = torch.zeros_like(directions)
    origin[:, 1] = planet_radius + eye_height
    _, t_top = intersect_sphere(origin, directions, centre, atmosphere_radius)
    g_near, _ = intersect_sphere(origin, directions, centre, planet_radius)
    t_end = torch.where(g_near > 0, torch.minimum(g_near, t_top), t_top).clamp_min(0.0)
    dt = t_end / steps
    cos = (directions * sun_dir).sum(dim=1)
    optical_r = torch.zeros_like(dt)
    optical_m = torch.zeros_like(dt)
    sum_r = torch.zeros_like(directions)
    sum_m = torch.zeros_like(directions)
    for i in range(steps):
        p = origin + ((i + 0.5) * dt)[:, None] * directions
        height = p.norm(dim=1) - planet_radius
        hr = torch.exp(-height / rayleigh_height) * dt
        hm = torch.exp(-height / mie_height) * dt
        optical_r, optical_m = optical_r + hr, optical_m + hm
        # towards the sun: to the top of the atmosphere, in shadow if the planet is in the way
        _, l_top = intersect_sphere(p, sun_dir, centre, atmosphere_radius)
        l_near, _ = intersect_sphere(p, sun_dir, centre, planet_radius)
        lit = ~(l_near > 0)
        ldt = l_top.clamp_min(0.0) / light_steps
        light_r = torch.zeros_like(dt)
        light_m = torch.zeros_like(dt)
        for j in range(light_steps):
            q = p + ((j + 0.5) * ldt)[:, None] * sun_dir
            h = q.norm(dim=1) - planet_radius
            light_r = light_r + torch.exp(-h / rayleigh_height) * ldt
            light_m = light_m + torch.exp(-h / mie_height) * ldt
        tau = rayleigh * (optical_r + light_r)[:, None] + (1.1 * mie * (optical_m + light_m))[:, None]
        attenuation = torch.exp(-tau) * lit[:, None]
        sum_r = sum_r + attenuation * hr[:, None]
        sum_m = sum_m + attenuation * hm[:, None]
    return sun_intensity[:, None] * (
        sum_r * rayleigh * rayleigh_phase(cos)[:, None] + sum_m * (mie * mie_cornette_shanks(cos, mie_g))[:, None]
    )


def _atmosphere(sky: Stacked, directions: Tensor, s: Tensor, sun: Tensor) -> Tensor:
    atm = sky.atmosphere
    per_ray = {k: take(getattr(atm, k), s) for k in (
        "planet_radius", "eye_height", "rayleigh", "mie", "rayleigh_height", "mie_height", "mie_g", "sun_intensity")}
    return atmosphere_sky(directions, take(sun, s), steps=atm.steps, light_steps=atm.light_steps,
                          atmosphere_radius=take(atm.planet_radius + atm.atmosphere_height, s), **per_ray)


SKIES = Registry("sky")
SKIES.register("constant", ConstantSky, lambda sky, d, s, sun: take(sky.radiance, s))
SKIES.register("gradient", GradientSky, lambda sky, d, s, sun: gradient_sky(d, take(sky.horizon, s), take(sky.slope, s)))
SKIES.register("atmosphere", AtmosphereSky, _atmosphere, needs_sun=True)
