"""The physical medium: single scattering from each light with its shadow transmittance, plus
emission, L = ∫ T(t) [σs(t) Σ p(θ) E T_light(t) + σe(t)] dt, as plain functions of a render's
state (`ctx`: the batch's lights, counts and timer) and one volume's state (`vol`: its parameters,
field, bounds, phase and planned lights). Where the volume asks for them, the lights' in-scatter
is summed over Wrenninge's octaves (`multiple.py`) and sky light is scattered in (`ambient.py`)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..geometry.camera import Rays
from ..ops import lanes
from ..schema.batch import take
from .ambient import ambient_in_scatter
from .composite import VolumePart
from .context import VolumeContext
from .emission import EMISSION_MAPS, bloom_glow
from .integrate import frostbite_step
from .march import (
    LN2,
    Medium,
    expected_depth_fraction,
    gathered,
    lod_drop,
    median_crossing,
)
from .multiple import octave_response, octave_sum, octave_weights
from .shadow import line_depth, occluder_transmittance, shadow_transmittance, sun_grids


def phase(vol, cos: Tensor, s: Tensor) -> Tensor:
    """The volume's phase function at `cos` [n] of scenes `s` [n] -> [n]."""
    return vol.phase.fn(vol.params.phase.value, cos, s)


def response(vol, irradiance: Tensor, cos: Tensor, s: Tensor) -> Tensor:
    """E · p(θ) [n, 3] of a light of irradiance [n, 3] at cos θ [n]; with multiple scattering
    each octave's [n, K, 3]."""
    if vol.plan.multiple:
        return octave_response(vol, irradiance, cos, s)
    return irradiance * phase(vol, cos, s)[:, None]


def light_responses(ctx: VolumeContext, vol, d: Tensor, s: Tensor) -> list[Tensor | None]:
    """`response` of each directional light along directions `d` [n, 3] of scenes `s` [n]; None
    for a light that is not directional. A sun's θ is the same all along a ray: a march computes
    this once per ray."""
    out = []
    for light in ctx.lights:
        if light.directional:  # as it leaves the sun: `in_scatter` applies the air at each sample
            toward = light.leaving(d, s)
            out.append(response(vol, toward.irradiance, (d * toward.direction).sum(dim=1), s))
        else:
            out.append(None)
    return out


def in_scatter(ctx: VolumeContext, vol, p: Tensor, d: Tensor | None, s: Tensor, sigma_t: Tensor, responses: list[Tensor | None],
               density: Tensor) -> Tensor:
    """Σ over the volume's lights of σs · p(θ) · E · T_light at points `p` [n, 3] seen along `d`
    [n, 3], of extinction `sigma_t` [n] (summed over octaves with multiple scattering), plus the
    ambient's σs · L_amb · V; `responses`: `light_responses` at these samples (`d` is needed only
    where one is None: a light that is not directional); `density` [n] the field's there (where a
    closed-form shadow starts). -> [n, 3]."""
    out = p.new_zeros(p.shape[0], 3)
    sigma_s = take(vol.params.albedo, s) * sigma_t
    for use in vol.plan.lights:
        light, toward = ctx.lights[use.light], None
        resp = responses[use.light]
        if resp is None:
            toward = light.toward(p, s)
            resp = response(vol, toward.irradiance, (d * toward.direction).sum(dim=1), s)
        trans = None
        if use.shadow is not None:
            with ctx.timer.section(use.name):
                trans = light_transmittance(ctx, vol, use, p, s, sigma_t, toward, density)
        if vol.plan.multiple:
            radiance = octave_sum(vol, resp, sigma_s, trans, s)
        else:  # octave 0 alone: single scattering is the octaves' first term, to the bit
            radiance = resp * octave_weights(sigma_s, trans, [])[0][:, None]
        if toward is None and light.through is not None:  # a per-ray response: the air on the sun's way to p
            radiance = radiance * light.through(p, s)
        out = out + radiance
    if vol.plan.ambient:
        out = out + ambient_in_scatter(ctx, vol, p, s, sigma_s, density)
    return out


def light_transmittance(ctx: VolumeContext, vol, use, p: Tensor, s: Tensor, sigma_t: Tensor, toward, density: Tensor) -> Tensor:
    """Transmittance [n] from `p` [n, 3] towards light `use.light` through this volume, ending where
    the ray leaves the bounds or reaches the light; `sigma_t` [n] the extinction at `p`, `density`
    [n] the field's (a closed form starts from it: no evaluation). Times what
    the plan's other occluders let through (other volumes, the terrain, the voxels), where it names any."""
    shadow = use.shadow
    light = ctx.lights[use.light]
    direction = take(light.direction, s) if toward is None else toward.direction
    distance = p.new_full((p.shape[0],), math.inf) if toward is None else toward.distance
    grid = shadow.method == "grid" and not vol.plan.line_integral  # (a closed form is exact: no grid)
    exit_t = None if grid else torch.minimum(vol.intersect(p, direction, s)[1].clamp(0.0, vol.plan.reach), distance)
    if grid:
        own = sun_grids(ctx, vol, use.light).lookup(p, sigma_t, s)
    elif vol.plan.line_integral:  # exact: no march
        own = torch.exp(-take(vol.params.sigma_t, s) * line_depth(vol, p, s, direction, exit_t, density))
    else:
        own = shadow_transmittance(
            p, direction, exit_t, lambda q, owner: take(vol.params.sigma_t, s[owner]) * vol.field(q, s[owner]),
            steps=shadow.steps, growth=shadow.growth, first_step=shadow.first_step,
        )
    if use.occluders or use.terrain or use.voxels:
        own = own * occluder_transmittance(ctx, use, p, s, direction, distance)
    return own


def physical_medium(ctx: VolumeContext, vol, rays: Rays, background: Tensor | None, *, signed: bool = False) -> Medium:
    """The medium of a physically shaded volume: (σ_t [n], in-scattered + emitted source [n, 3]).
    `signed`: σ_t is the field's signed value times its σ_t, negative where there is no density
    (what `march_adaptive` interpolates between samples); the source is that of the density."""
    o, d, s_all = rays.origins, rays.directions, rays.scene_index
    threshold, lod_scale = ctx.settings.density_threshold, ctx.settings.lod_scale
    responses = light_responses(ctx, vol, d, s_all) if vol.plan.lights else []
    lights = bool(vol.plan.lights) or vol.plan.ambient
    at = gathered(lambda ids: (s_all[ids], o[ids], d[ids], [None if r is None else r[ids] for r in responses]))
    field = vol.field.signed if signed else vol.field

    def medium(ids: Tensor, t: Tensor, dt: Tensor):
        s, o_ids, d_ids, resp = at(ids)
        p = torch.addcmul(o_ids, t[:, None], d_ids)
        raw = field(p, s, lod_drop(t, lod_scale))
        density = raw.clamp_min(0.0) if signed else raw
        sigma_raw = take(vol.params.sigma_t, s) * raw
        sigma_t = sigma_raw.clamp_min(0.0) if signed else sigma_raw
        source = p.new_zeros(p.shape[0], 3)
        if lights:
            lit = ((density > threshold) & (dt > 0)).nonzero().squeeze(1)  # dt = 0: a finished ray not dropped yet
            if lit.numel():
                d_lit = d_ids[lit] if any(r is None for r in resp) else None  # only point lights need it per sample
                source[lit] = in_scatter(ctx, vol, p[lit], d_lit, s[lit], sigma_t[lit],
                                         [None if r is None else r[lit] for r in resp], density[lit])
        if vol.plan.emissive:
            source = source + take(vol.params.emission, s) * density[:, None]
        if vol.plan.emission_map is not None:
            with ctx.timer.section(vol.plan.emission_pass):
                source = source + EMISSION_MAPS[vol.plan.emission_map].fn(vol.params.emission_map.value, p, density, s)
        if vol.plan.bloom is not None:
            with ctx.timer.section(vol.plan.bloom_pass):
                source = source + bloom_glow(vol.params.bloom, ctx.lights[vol.plan.bloom].params, p, s)
        if vol.plan.sky_blend:
            behind = lanes.columns(background[ids]) if background is not None else [0.0] * 3
            source = torch.stack(sky_blend(lanes.columns(source), behind, sigma_t, take(vol.params.sky_blend, s), t), 1)
        return sigma_raw, source

    return medium


def sky_blend(source, sky, sigma_t, k, t) -> list:
    """A sample's `source` (three lanes) blended into the `sky` behind its ray (three lanes, or
    numbers) with distance `t`: by 1 − e^(−k·t²), towards σt·sky, which integrates to the sky
    seen through the sample's opacity; `sigma_t` its extinction, `k` the volume's ``sky_blend``.
    Lanes (`ops.lanes`): eager and the kernel's sample alike. -> three lanes."""
    w = sky_blend_weight(k, t)
    return [lanes.lerp(source[c], sigma_t * sky[c], w) for c in range(3)]


def sky_blend_weight(k, t):
    """How far a sample at distance `t` along its camera ray blends into the sky, 1 − e^(−k·t²)
    (`k` the volume's ``sky_blend``); lanes: the march's blend and the paths' (`volume.path`)."""
    return -lanes.expm1(-k * t * t)


def exact_segment(source: Tensor, sigma_t: Tensor, a: Tensor, length: Tensor,
                  front: Tensor | None = None) -> dict[str, Tensor]:
    """One homogeneous segment [a, a + length] (each [n]) of extinction `sigma_t` [n] and source
    `source` [n, C], integrated exactly: its radiance [n, C], transmittance, weight sums Σw and
    Σwt (at the expected termination depth) and median t (0: T stays above 0.5), each [n]; with
    `front` [n] (the ray's transmittance at `a`, as `march.march`'s `transmittance`), the whole ray's."""
    radiance, trans = frostbite_step(source, sigma_t, length)
    if front is None:
        median = torch.where(trans <= 0.5, a + LN2 / sigma_t.clamp_min(torch.finfo(a.dtype).tiny), torch.zeros_like(a))
    else:
        radiance, crossed = radiance * front[:, None], (front > 0.5) & (front * trans <= 0.5)
        median = torch.where(crossed, median_crossing(a, front, sigma_t, length), torch.zeros_like(a))
        trans = front * trans
    alpha = (1.0 if front is None else front) - trans
    t_mean = a + length * expected_depth_fraction(sigma_t * length)
    return dict(radiance=radiance, transmittance=trans, weight_sum=alpha, weighted_t=alpha * t_mean, median_t=median)


def closed_form(ctx: VolumeContext, vol, rays: Rays, t0: Tensor, t1: Tensor, hit: Tensor) -> VolumePart:
    """Homogeneous medium, unshadowed directional lights: one exact frostbite segment over the
    whole chord, evaluated on the rays that hit only."""
    n = len(rays)
    out = dict(radiance=t0.new_zeros(n, 3), transmittance=torch.ones_like(t0), weight_sum=torch.zeros_like(t0),
               weighted_t=torch.zeros_like(t0), median_t=torch.zeros_like(t0), t0=torch.full_like(t0, math.inf))
    ids = hit.nonzero().squeeze(1)
    if ids.numel() == 0:
        return VolumePart(**out)
    s, d, a, b = rays.scene_index[ids], rays.directions[ids], t0[ids], t1[ids]
    length = b - a
    mid = rays.origins[ids] + (0.5 * (a + b))[:, None] * d
    density = vol.field(mid, s)
    sigma_t = take(vol.params.sigma_t, s) * density
    source = take(vol.params.emission, s) * density[:, None]
    if vol.plan.lights:
        source = source + in_scatter(ctx, vol, mid, d, s, sigma_t, light_responses(ctx, vol, d, s), density)
    for key, value in dict(exact_segment(source, sigma_t, a, length), t0=a).items():
        out[key][ids] = value
    return VolumePart(**out)
