"""The atmosphere (seed 000, variant 2): a planet-scale spherical shell of exponential Rayleigh and
Mie densities, each with its own scale height, single scattering of the sun with the seeds' nested
optical-depth march towards it. One function, `single_scatter`, serves both the `atmosphere` sky
(`torchvol.light.sky`: the shell seen from a fixed height, as a background) and the top-level
`[atmosphere]` medium (`aerial_perspective`: the scene inside the shell, whose ground y = 0 is the
planet's surface, centre (0, −R, 0), with the camera anywhere: on the ground, in the air, in space).

The medium is a pass after compositing: along each camera ray, what the scene's volumes and voxels
composited (at their depth) is attenuated by the air in front of it and the air's in-scatter is
added; behind what is not opaque lie the air beyond and the planet's ground (Lambertian, lit by
the sun through the air, opaque).

Lengths are world units (the defaults are Earth's in metres); coefficients are per world unit at
the ground. Mie extinction is 1.1 × its scattering (the seeds' aerosol absorption).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
from pydantic import Field, field_validator
from torch import Tensor

from ..geometry.rays import intersect_sphere
from ..schema.batch import Stacked, take
from ..schema.models import Strict, Vec3, nonneg
from .phase import mie_cornette_shanks
from .phase import rayleigh as rayleigh_phase

MIE_EXTINCTION = 1.1  # Mie extinction / Mie scattering


class AirLayer(Strict):
    """The shell and its air, shared by the `atmosphere` sky and the `[atmosphere]` medium."""

    planet_radius: float = Field(6.36e6, gt=0.0)
    atmosphere_height: float = Field(6.0e4, gt=0.0)
    rayleigh: Vec3 = (5.8e-6, 13.5e-6, 33.1e-6)
    mie: float = Field(21e-6, ge=0.0)
    rayleigh_height: float = Field(7994.0, gt=0.0)
    mie_height: float = Field(1200.0, gt=0.0)
    mie_g: float = Field(0.76, gt=-1.0, lt=1.0)
    steps: int | None = Field(None, ge=1, le=1024, description="None: the quality level's")
    light_steps: int | None = Field(None, ge=1, le=1024, description="None: the quality level's")
    _r = field_validator("rayleigh")(lambda v: nonneg(v))


class AtmosphereMedium(AirLayer):
    """The top-level `[atmosphere]`: the scene inside the shell (ground y = 0, planet centre
    (0, −planet_radius, 0)), lit by lights[0], a sun; `ground` is the planet surface's albedo."""

    ground: Vec3 = (0.3, 0.3, 0.3)
    _g = field_validator("ground")(lambda v: nonneg(v))


@dataclass(frozen=True)
class Air:
    """An `AirLayer` gathered per ray: radii, scale heights, `mie`, `mie_g` [n]; `rayleigh` [n, 3]."""

    planet_radius: Tensor
    top_radius: Tensor
    rayleigh: Tensor
    mie: Tensor
    scale_heights: Tensor  # [n, 2]: Rayleigh's, Mie's
    mie_g: Tensor


def gather_air(layer: Stacked, s: Tensor) -> Air:
    """The layer's values (B, ...) at the scenes `s` [n] of the rays."""
    return Air(planet_radius=take(layer.planet_radius, s), top_radius=take(layer.planet_radius + layer.atmosphere_height, s),
               rayleigh=take(layer.rayleigh, s), mie=take(layer.mie, s), mie_g=take(layer.mie_g, s),
               scale_heights=take(torch.stack([layer.rayleigh_height, layer.mie_height], dim=1), s))


def densities(points: Tensor, air: Air) -> Tensor:
    """The seeds' `density(p, H) = exp(−max(|p| − R, 0) / H)` for both scale heights: `points` [n, 3]
    relative to the planet's centre -> [n, 2] (Rayleigh, Mie)."""
    height = (points.norm(dim=1) - air.planet_radius).clamp_min(0.0)
    return torch.exp(-height[:, None] / air.scale_heights)


def optic_depth(start: Tensor, direction: Tensor, length: Tensor, air: Air, steps: int) -> Tensor:
    """The seeds' `opticDepth(from, to)`: ∫ density over the segment from `start` [n, 3] (planet
    frame) along unit `direction` [n, 3] for `length` [n], by the midpoint rule with `steps` steps
    -> [n, 2] (Rayleigh, Mie) in density × length."""
    ds = length / steps
    depth = start.new_zeros(start.shape[0], 2)
    for j in range(steps):
        depth = depth + densities(start + ((j + 0.5) * ds)[:, None] * direction, air) * ds[:, None]
    return depth


def extinction(depth: Tensor, air: Air) -> Tensor:
    """Optical thickness per colour [n, 3] of optic depths `depth` [n, 2] (Rayleigh, Mie)."""
    return air.rayleigh * depth[:, :1] + (MIE_EXTINCTION * air.mie * depth[:, 1])[:, None]


def sun_path(points: Tensor, sun_dir: Tensor, air: Air) -> tuple[Tensor, Tensor]:
    """From `points` [n, 3] (planet frame) towards the sun `sun_dir` [n, 3]: the distance to the top
    of the atmosphere [n] (0 outside it, going away) and whether the planet blocks the sun [n]."""
    _, top = intersect_sphere(points, sun_dir, torch.zeros_like(points), air.top_radius)
    near, far = intersect_sphere(points, sun_dir, torch.zeros_like(points), air.planet_radius)
    return top.clamp_min(0.0), (near > 0) & (near <= far)  # a miss is (inf, -inf): not in the way


def single_scatter(origins: Tensor, directions: Tensor, t0: Tensor, t1: Tensor, sun_dir: Tensor, air: Air, *,
                   steps: int, light_steps: int) -> tuple[Tensor, Tensor]:
    """Single scattering of the sun by the air on the segment [t0, t1] [n] of rays `origins`,
    `directions` [n, 3] (planet frame, unit directions), `steps` midpoint samples, each with
    `light_steps` towards the sun `sun_dir` [n, 3] (unit). -> (in-scatter [n, 3] per unit sun
    irradiance, seen from t0; transmittance [n, 3] from t0 to t1). t1 ≤ t0 gives (0, 1)."""
    dt = (t1 - t0).clamp_min(0.0) / steps
    cos = (directions * sun_dir).sum(dim=1)
    optical = torch.zeros_like(air.scale_heights)
    sums = directions.new_zeros(directions.shape[0], 2, 3)  # Rayleigh's and Mie's attenuated sums
    for i in range(steps):
        p = origins + (t0 + (i + 0.5) * dt)[:, None] * directions
        step = densities(p, air) * dt[:, None]
        optical = optical + step
        length, blocked = sun_path(p, sun_dir, air)
        attenuation = torch.exp(-extinction(optical + optic_depth(p, sun_dir, length, air, light_steps), air))
        sums = sums + (attenuation * ~blocked[:, None])[:, None, :] * step[:, :, None]
    inscatter = (sums[:, 0] * air.rayleigh * rayleigh_phase(cos)[:, None]
                 + sums[:, 1] * (air.mie * mie_cornette_shanks(cos, air.mie_g))[:, None])
    return inscatter, torch.exp(-extinction(optical, air))


def _segments(mask: Tensor, origins: Tensor, directions: Tensor, t0: Tensor, t1: Tensor, sun_dir: Tensor, air: Air,
              steps: int, light_steps: int) -> tuple[Tensor, Tensor]:
    """`single_scatter` of the rays where `mask` [n]; the others get an empty segment's (0, 1)."""
    inscatter, trans = torch.zeros_like(origins), torch.ones_like(origins)
    rays = mask.nonzero().squeeze(1)
    if rays.numel():
        part = Air(**{f.name: getattr(air, f.name)[rays] for f in fields(air)})
        inscatter[rays], trans[rays] = single_scatter(origins[rays], directions[rays], t0[rays], t1[rays], sun_dir[rays],
                                                      part, steps=steps, light_steps=light_steps)
    return inscatter, trans


def planet_frame(origins: Tensor, air: Air) -> Tensor:
    """World points [n, 3] (ground y = 0) -> relative to the planet's centre (0, −R, 0)."""
    return origins + torch.stack([torch.zeros_like(air.planet_radius), air.planet_radius,
                                  torch.zeros_like(air.planet_radius)], dim=1)


def ground_distance(origins: Tensor, directions: Tensor, planet_radius: Tensor) -> Tensor:
    """Distance [n] along world rays `origins`, `directions` [n, 3] (unit) to the planet's surface
    in front of them (radius `planet_radius` [n], centre (0, −R, 0)); inf where they miss it or
    start below it. The ray/sphere roots with c = |o − centre|² − R² written |o|² + 2R·y: no
    cancellation near the ground (the sphere test in the planet's frame, R² ≈ 4e13 in float32, puts
    a camera 2 m up at 1.5–2.5 m)."""
    c = (origins * origins).sum(dim=1) + 2.0 * planet_radius * origins[:, 1]
    b = (origins * directions).sum(dim=1) + planet_radius * directions[:, 1]
    disc = b * b - c
    hit = (c > 0) & (b < 0) & (disc >= 0)  # above the ground, heading down, meeting the sphere
    q = torch.where(hit, disc.clamp_min(0.0).sqrt() - b, torch.ones_like(b))  # −b + √disc > 0: no cancellation
    return torch.where(hit, c / q, torch.full_like(b, math.inf))


def aerial_perspective(radiance: Tensor, alpha: Tensor, distance: Tensor, origins: Tensor, directions: Tensor,
                       sun_dir: Tensor, sun: Tensor, ground: Tensor, air: Air, *, steps: int,
                       light_steps: int) -> tuple[Tensor, Tensor]:
    """The scene seen through the atmosphere medium.

    `radiance` [n, 3], `alpha`, `distance` [n]: what the scene composited along each ray and at
    which distance (0: nothing there); `origins`, `directions` [n, 3] world rays; `sun_dir` [n, 3]
    towards the sun, `sun` [n, 3] its irradiance; `ground` [n, 3] the planet's albedo. The air in
    front of the scene's depth attenuates it and adds its in-scatter; where the scene is not
    opaque (1 − alpha) the air behind it and the planet's ground show through.
    -> (radiance [n, 3], distance to the ground [n], 0 where the ray does not reach it)."""
    o = planet_frame(origins, air)
    centre = torch.zeros_like(o)
    top_near, top_far = intersect_sphere(o, directions, centre, air.top_radius)
    inside = top_far > 0  # a miss is (inf, -inf)
    enter = torch.where(inside, top_near.clamp_min(0.0), torch.zeros_like(top_far))
    leave = torch.where(inside, top_far, torch.zeros_like(top_far))
    g_near = ground_distance(origins, directions, air.planet_radius)
    hits_ground = inside & (g_near < leave)
    leave = torch.where(hits_ground, g_near, leave)
    depth = torch.minimum(torch.maximum(distance, enter), leave)  # the scene's depth, inside the air
    # an empty segment scatters nothing and transmits all: march only the rays with air in front of
    # the scene's depth, and behind it only where the scene is not opaque
    front, t_front = _segments(depth > enter, o, directions, enter, depth, sun_dir, air, steps, light_steps)
    back, t_back = _segments((leave > depth) & (alpha < 1.0), o, directions, depth, leave, sun_dir, air, steps,
                             light_steps)
    # the ground: Lambertian, lit by the sun through the air above it
    p = o + leave[:, None] * directions
    normal = p / p.norm(dim=1, keepdim=True)
    length, _ = sun_path(p, sun_dir, air)
    lit = torch.exp(-extinction(optic_depth(p, sun_dir, length, air, light_steps), air))
    cos = (normal * sun_dir).sum(dim=1).clamp_min(0.0) * hits_ground
    floor = ground / math.pi * sun * lit * cos[:, None]
    behind = sun * back + t_back * floor
    out = sun * front + t_front * (radiance + (1.0 - alpha)[:, None] * behind)
    return out, torch.where(hits_ground, g_near, torch.zeros_like(leave))
