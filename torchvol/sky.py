"""Sky radiance along view directions: constant, the seeds' gradient, and the sun's glow lobes."""

from __future__ import annotations

import torch
from torch import Tensor


def gradient_sky(directions: Tensor, horizon: Tensor, slope: Tensor) -> Tensor:
    """The template's `bgcol = horizon − rd.y · slope`. `directions`: [R, 3]; `horizon`, `slope`:
    [R, 3] (gathered per ray). -> [R, 3]."""
    return horizon - directions[:, 1:2] * slope


def sun_glow(directions: Tensor, sun_dir: Tensor, color: Tensor, power: Tensor) -> Tensor:
    """color · clamp(dot(sun, rd), 0, 1)^power: the template's halo (power 8) and flare (power 3).
    `directions`, `sun_dir`, `color`: [R, 3]; `power`: [R]. -> [R, 3]."""
    sun = (directions * sun_dir).sum(dim=1).clamp(0.0, 1.0)
    return color * sun.pow(power)[:, None]


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
    from .rays import intersect_sphere
    from .volume.light import mie_cornette_shanks, rayleigh as rayleigh_phase

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
