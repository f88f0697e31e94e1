"""The atmosphere (seed 000, variant 2): a planet-scale spherical shell of exponential Rayleigh and
Mie densities, each with its own scale height, single scattering of the sun with the seeds' nested
optical-depth march towards it. One function, `single_scatter`, serves both the `atmosphere` sky
(`torchvol.light.sky`: the shell seen from a fixed height, as a background) and the top-level
`[atmosphere]` medium (`AirPath`: the scene inside the shell, whose ground y = 0 is the
planet's surface, centre (0, −R, 0), with the camera anywhere: on the ground, in the air, in space).

The medium is one of the media of the camera rays' march (`AirPath`, marched with the volumes by
`volume.joint`): every sample's light reaches the camera through the air in front of it, the
air's in-scatter is summed in every piece of the ray inside the shell, and behind everything lie
the planet's ground (Lambertian, lit by the sun through the air, opaque) or space. The sun that
reaches any point of the scene (a volume's sample, a voxel face, the terrain) comes through the
air (`sun_transmittance`, the lights' `through`).

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


def shell_span(origins: Tensor, directions: Tensor, air: Air) -> tuple[Tensor, Tensor, Tensor]:
    """Where world rays `origins`, `directions` [n, 3] (unit) are in the air: (enter, leave [n]:
    both 0 for a ray that misses the shell; leave is the ground where the ray meets it first,
    ground [n]: the distance to the planet's surface, inf where the ray does not reach it)."""
    o = planet_frame(origins, air)
    top_near, top_far = intersect_sphere(o, directions, torch.zeros_like(o), air.top_radius)
    inside = top_far > 0  # a miss is (inf, -inf)
    enter = torch.where(inside, top_near.clamp_min(0.0), torch.zeros_like(top_far))
    leave = torch.where(inside, top_far, torch.zeros_like(top_far))
    g_near = ground_distance(origins, directions, air.planet_radius)
    ground = torch.where(inside & (g_near < leave), g_near, torch.full_like(g_near, math.inf))
    return enter, torch.minimum(leave, ground), ground


def sun_transmittance(points: Tensor, sun_dir: Tensor, air: Air, light_steps: int) -> Tensor:
    """The air's transmittance [n, 3] from `points` [n, 3] (planet frame) to the sun `sun_dir`
    [n, 3] (unit): the nested optical-depth march, 0 where the planet is in the way."""
    length, blocked = sun_path(points, sun_dir, air)
    return torch.exp(-extinction(optic_depth(points, sun_dir, length, air, light_steps), air)) * ~blocked[:, None]


def ground_radiance(points: Tensor, sun_dir: Tensor, sun: Tensor, albedo: Tensor, air: Air, light_steps: int) -> Tensor:
    """The planet's ground at `points` [n, 3] (planet frame, on the surface): Lambertian of `albedo`
    [n, 3], lit by the sun (`sun_dir` [n, 3], irradiance `sun` [n, 3]) through the air. -> [n, 3]."""
    normal = points / points.norm(dim=1, keepdim=True)
    cos = (normal * sun_dir).sum(dim=1).clamp_min(0.0)
    return albedo / math.pi * sun * sun_transmittance(points, sun_dir, air, light_steps) * cos[:, None]


def rows_of(air: Air, rows: Tensor) -> Air:
    """The rays `rows` [m] of `air` (gathered per ray)."""
    return Air(**{f.name: getattr(air, f.name)[rows] for f in fields(air)})


@dataclass(frozen=True)
class AirPath:
    """The air along a chunk's camera rays, as a medium of their march (`volume.joint`): `origins`
    (planet frame), `directions` [n, 3]; `enter`, `leave`, `ground` [n] (`shell_span`); the optical
    depth from the camera at K + 1 even nodes over [enter, leave] (`depth` [n, K + 1, 3]); the
    sun's direction and irradiance [n, 3]; the air [n] and its `light_steps`."""

    origins: Tensor
    directions: Tensor
    enter: Tensor
    leave: Tensor
    ground: Tensor
    depth: Tensor
    sun_dir: Tensor
    sun: Tensor
    air: Air
    light_steps: int

    def transmittance(self, rows: Tensor, t: Tensor) -> Tensor:
        """The air's transmittance [m, 3] from the camera to distance `t` [m] along rays `rows` [m]
        (the table interpolated linearly: exact where the air is homogeneous)."""
        k = self.depth.shape[1] - 1
        enter, span = self.enter[rows], (self.leave[rows] - self.enter[rows]).clamp_min(torch.finfo(t.dtype).tiny)
        u = ((t - enter) / span).clamp(0.0, 1.0) * k
        lo = u.floor().clamp(max=k - 1).long()
        table = self.depth[rows]
        a, b = table.gather(1, lo[:, None, None].expand(-1, 1, 3))[:, 0], table.gather(1, (lo + 1)[:, None, None].expand(-1, 1, 3))[:, 0]
        return torch.exp(-torch.lerp(a, b, (u - lo)[:, None]))

    def source(self, rows: Tensor, t: Tensor) -> Tensor:
        """The sun's light scattered by the air towards the camera per unit length [m, 3] at
        distance `t` [m] along rays `rows` [m] (not yet attenuated on the way to the camera)."""
        air, d, sun_dir = rows_of(self.air, rows), self.directions[rows], self.sun_dir[rows]
        p = self.origins[rows] + t[:, None] * d
        density = densities(p, air)
        cos = (d * sun_dir).sum(dim=1)
        scatter = (density[:, :1] * air.rayleigh * rayleigh_phase(cos)[:, None]
                   + (density[:, 1] * air.mie * mie_cornette_shanks(cos, air.mie_g))[:, None])
        return self.sun[rows] * sun_transmittance(p, sun_dir, air, self.light_steps) * scatter


def air_path(origins: Tensor, directions: Tensor, sun_dir: Tensor, sun: Tensor, air: Air, *, steps: int,
             light_steps: int) -> AirPath:
    """The `AirPath` of world rays `origins`, `directions` [n, 3] lit by the sun `sun_dir` [n, 3]
    (irradiance `sun` [n, 3]): the optical depth tabulated at `steps` + 1 nodes (the midpoint rule
    between them), `light_steps` for the march towards the sun."""
    o = planet_frame(origins, air)
    enter, leave, ground = shell_span(origins, directions, air)
    dt = (leave - enter).clamp_min(0.0) / steps
    depth = [torch.zeros_like(o)]
    for i in range(steps):
        p = o + (enter + (i + 0.5) * dt)[:, None] * directions
        depth.append(depth[-1] + extinction(densities(p, air) * dt[:, None], air))
    return AirPath(o, directions, enter, leave, ground, torch.stack(depth, dim=1), sun_dir, sun, air, light_steps)
