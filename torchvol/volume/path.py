"""Path tracing of the physical media (`[path]`): every order of scattering, unbiased.

Each camera ray sends `[path].samples` paths. A path flies through every medium of the scene at
once by delta tracking against a majorant per medium (their sum along the ray), and at each real
collision collects the medium's emission (σe/σt), then, while it has scattered fewer than
`bounces` times, the light of every light source by next-event estimation (the phase function
times the light's irradiance times the transmittance towards it, by ratio tracking through every
medium), and scatters: its throughput times the albedo, a new direction drawn from the phase
function. A path that leaves the media sees the sky. Russian roulette ends paths of low throughput
past `ROULETTE_AFTER` scatterings without bias. So `bounces = B` sums the light that scattered at
most B times: B = 1 is the single-scattering integral the physical march computes.

Majorants (`majorant`): exact where the density has a known bound (constant, grid, exponential),
else the largest of a lattice of samples over the volume's box times `MARGIN`. The tracking is
weighted (Kutz et al. 2017): where a density exceeds its majorant the estimate stays unbiased,
only noisier, and `stats["path"]["above_majorant"]` counts those collisions.

Random numbers are a counter-based hash of (scene seed, pixel, sample, draw): a path's numbers
depend on nothing else, so a sample's bytes do not depend on the batch, chunking or threads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import torch
from torch import Tensor

from ..noise.lattice import hash3
from ..schema.batch import take

ROULETTE_AFTER = 3  # scatterings before Russian roulette may end a path
MARGIN = 1.5  # an estimated majorant: the largest lattice sample times this
LATTICE = 24  # samples a side of the lattice an estimated majorant comes from
MAX_TENTATIVE = 100_000  # tentative collisions a tracking call takes at most (then it stops: counted)
FADE = 0.05  # a ratio-tracked transmittance below this plays Russian roulette
_KEY, _DRAW = 0x7A17, 0x5CA7


@dataclass
class PathCounts:
    """What a render's paths did: collisions above a majorant, trackings cut at MAX_TENTATIVE."""

    above_majorant: int = 0
    truncated: int = 0


@dataclass
class Media:
    """The physically shaded volumes a path meets (`vols`, the render's volume states), each
    one's majorant of σ_t per scene (`majorants` (B,)), and the render's counts."""

    vols: list
    majorants: list[Tensor]
    counts: PathCounts = field(default_factory=PathCounts)


class Draws:
    """Uniform numbers in [0, 1) for paths of keys `key` [n] (long): draw k of path i is a hash of
    (key[i], k), its counter advanced per draw."""

    def __init__(self, key: Tensor, dtype: torch.dtype):
        self.key, self.count, self.dtype = key, torch.zeros_like(key), dtype

    def __call__(self, ids: Tensor) -> Tensor:
        cells = torch.stack([self.key[ids], self.count[ids], torch.zeros_like(ids)], dim=1)
        self.count.index_add_(0, ids, torch.ones_like(ids))
        return hash3(cells, _DRAW, dtype=self.dtype)


def path_keys(keys: Tensor, sample: int, samples: int) -> Tensor:
    """Each ray's path key [n] for path `sample` of `samples`: a hash of its ray key [n, 3] (pixel
    column·spp + sub-sample, row, scene seed) with the sample, as a 32-bit integer."""
    cells = torch.stack([keys[:, 0] * samples + sample, keys[:, 1], keys[:, 2]], dim=1)
    return (hash3(cells, _KEY, dtype=torch.float64) * 2.0**32).to(torch.long)


def majorant(vol, dtype: torch.dtype) -> Tensor:
    """An upper bound (B,) of the volume's σ_t over its bounds: exact for constant, grid and
    exponential densities; else `MARGIN` × the largest σ_t on a `LATTICE`³ lattice of its box."""
    p, kind = vol.params, vol.params.density.kind
    inner = vol.field.inner
    while hasattr(inner, "inner"):  # an edge fade only lowers the density
        inner = inner.inner
    if kind == "constant":
        bound = p.density.value.to(dtype)
    elif kind == "grid":
        bound = torch.stack([g.max() for g in inner.grids]).to(dtype)
    elif kind == "exponential":
        e = p.density.value
        low = vol.bounds.caps["height_range"](p.bounds.value)[:, 0].to(dtype)
        bound = e.value.to(dtype) * torch.exp(((e.base - low) / e.scale_height).clamp(max=math.log(1e12)))
    else:
        bound = _lattice_maximum(vol, dtype) * MARGIN
    return p.sigma_t.to(dtype) * bound.clamp(max=1e12)


def _lattice_maximum(vol, dtype: torch.dtype) -> Tensor:
    """The largest density (B,) on a LATTICE³ lattice of cell centres of each scene's box."""
    aabb = vol.bounds.caps["aabb"]
    if aabb is None:
        raise ValueError(f"path: volumes with {vol.params.bounds.kind} bounds and a {vol.params.density.kind} density "
                         "have no bound on their density; use box, sphere or shell bounds")
    lo, hi = (x.to(dtype) for x in aabb(vol.params.bounds.value))
    u = (torch.arange(LATTICE, dtype=dtype, device=lo.device) + 0.5) / LATTICE
    grid = torch.stack(torch.meshgrid(u, u, u, indexing="ij"), dim=-1).reshape(-1, 3)
    out = []
    for b in range(lo.shape[0]):
        points = lo[b] + grid * (hi[b] - lo[b])
        out.append(vol.field(points, torch.full((points.shape[0],), b, device=lo.device)).max())
    return torch.stack(out)


def media(vols: list, dtype: torch.dtype) -> Media:
    """The paths' `Media` of the render's physically shaded volume states `vols`."""
    return Media(vols, [majorant(v, dtype) for v in vols])


def _intervals(m: Media, o: Tensor, d: Tensor, s: Tensor, t_max: Tensor):
    """Each volume's span [t0, t1] [V, n] along rays o, d [n, 3] of scenes s [n] up to t_max [n]
    (empty: t0 = t1), and the rays' summed majorant [n] over the volumes they cross."""
    t0, t1, total = [], [], o.new_zeros(o.shape[0])
    for v, maj in zip(m.vols, m.majorants):
        near, far = v.intersect(o, d, s)
        a, b = near.clamp_min(0.0), torch.minimum(torch.minimum(far, t_max), o.new_tensor(v.plan.reach))
        crosses = b > a
        t0.append(torch.where(crosses, a, torch.zeros_like(a)))
        t1.append(torch.where(crosses, b, torch.zeros_like(b)))
        total = total + torch.where(crosses, take(maj, s), torch.zeros_like(a))
    return torch.stack(t0), torch.stack(t1), total


def _extinctions(m: Media, x: Tensor, s: Tensor, t: Tensor, t0: Tensor, t1: Tensor) -> Tensor:
    """σ_t [V, n] of each volume at points x [n, 3] (distance t [n] along their rays, inside a
    volume's span [t0, t1] [V, n]; 0 outside it)."""
    out = x.new_zeros(len(m.vols), x.shape[0])
    for v, vol in enumerate(m.vols):
        inside = ((t >= t0[v]) & (t < t1[v])).nonzero().squeeze(1)
        if inside.numel():
            si = s[inside]
            out[v, inside] = take(vol.params.sigma_t, si) * vol.field(x[inside], si)
    return out


def _track(m: Media, o: Tensor, d: Tensor, s: Tensor, t_max: Tensor, draw: Draws, ids: Tensor, *, collide: bool):
    """Weighted delta tracking (`collide`) or ratio tracking along rays o, d [n, 3] of scenes s [n]
    up to t_max [n] through every medium, drawing for paths `ids` [n]. -> (t [n]: where a real
    collision happened, inf where the ray left; the volume [n] (−1: none); σ_t of that volume
    there [n]; the weight [n]: the tracking's weight, or the transmittance for ratio tracking)."""
    n = o.shape[0]
    t0, t1, total = _intervals(m, o, d, s, t_max)
    t = torch.where(total > 0, t0.masked_fill(t1 <= t0, math.inf).amin(dim=0), torch.full_like(total, math.inf))
    end = t1.amax(dim=0)
    hit_t, vol, sigma, weight = torch.full_like(t, math.inf), torch.full((n,), -1, dtype=torch.long), t.new_zeros(n), t.new_ones(n)
    live = (t < end).nonzero().squeeze(1)
    for _ in range(MAX_TENTATIVE):
        if not live.numel():
            break
        t[live] = t[live] - torch.log1p(-draw(ids[live])) / total[live]
        live = live[t[live] < end[live]]
        if not live.numel():
            break
        sig = _extinctions(m, o[live] + t[live, None] * d[live], s[live], t[live], t0[:, live], t1[:, live])
        sig_sum, bound = sig.sum(dim=0), total[live]
        m.counts.above_majorant += int((sig_sum > bound).sum())
        null = bound - sig_sum
        if not collide:  # ratio tracking: the transmittance's product of null fractions
            weight[live] = weight[live] * null / bound
            _fade(weight, live, draw, ids)
            live = live[weight[live] != 0]
            continue
        p_real = sig_sum / (sig_sum + null.abs())
        real = draw(ids[live]) < p_real
        # a real collision's weight (σ_t + |σ_n|)/σ̄, a null one's sign(σ_n) times it: 1 and 1 below the majorant
        scale = (sig_sum + null.abs()) / bound
        weight[live] = weight[live] * torch.where(real, scale, torch.sign(null) * scale)
        done = live[real]
        if done.numel():
            pick = draw(ids[done]) * sig_sum[real]  # the volume: by its share of σ_t
            k = (sig[:, real].cumsum(dim=0) <= pick[None]).sum(dim=0).clamp_max(len(m.vols) - 1)
            hit_t[done], vol[done], sigma[done] = t[done], k, sig[:, real].gather(0, k[None])[0]
        live = live[~real]
    else:
        m.counts.truncated += int(live.numel())
    return hit_t, vol, sigma, weight


def _fade(weight: Tensor, live: Tensor, draw: Draws, ids: Tensor) -> None:
    """Russian roulette on a ratio-tracked transmittance under FADE: kept at twice its value with
    probability ½, else 0 (unbiased; a dense medium's shadow ray then ends in a few steps)."""
    low = live[weight[live].abs() < FADE]
    if low.numel():
        keep = draw(ids[low]) < 0.5
        weight[low] = torch.where(keep, 2.0 * weight[low], torch.zeros_like(weight[low]))


def transmittance(m: Media, o: Tensor, d: Tensor, s: Tensor, t_max: Tensor, draw: Draws, ids: Tensor) -> Tensor:
    """Ratio-tracked transmittance [n] through every medium along rays o, d [n, 3] of scenes s [n]
    up to t_max [n] (an unbiased estimate; negative where a density exceeds its majorant)."""
    return _track(m, o, d, s, t_max, draw, ids, collide=False)[3]


def _basis(d: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit vectors [n, 3] completing unit d [n, 3] to an orthonormal basis (Duff et al. 2017)."""
    x, y, z = d.unbind(1)
    sign = torch.where(z >= 0, torch.ones_like(z), -torch.ones_like(z))
    a = -1.0 / (sign + z)
    b = x * y * a
    return (torch.stack([1.0 + sign * x * x * a, sign * b, -sign * x], dim=1),
            torch.stack([b, sign + y * y * a, -y], dim=1))


def _turn(d: Tensor, cos: Tensor, u: Tensor) -> Tensor:
    """The unit direction [n, 3] at angle acos(cos) [n] from d [n, 3], azimuth 2π·u [n]."""
    t1, t2 = _basis(d)
    sin = (1.0 - cos * cos).clamp_min(0.0).sqrt()
    phi = 2.0 * math.pi * u
    return (sin * torch.cos(phi))[:, None] * t1 + (sin * torch.sin(phi))[:, None] * t2 + cos[:, None] * d


def hg_cos(g: Tensor, u: Tensor) -> Tensor:
    """cos θ [n] drawn from Henyey-Greenstein g [n] by inverting its CDF at u [n] (|g| < 1e-3:
    isotropic)."""
    small = g.abs() < 1e-3
    gs = torch.where(small, torch.ones_like(g), g)
    q = (1.0 - gs * gs) / (1.0 - gs + 2.0 * gs * u)
    cos = (1.0 + gs * gs - q * q) / (2.0 * gs)
    return torch.where(small, 1.0 - 2.0 * u, cos).clamp(-1.0, 1.0)


def sample_phase(vol, d: Tensor, s: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
    """A new direction [n, 3] scattered from d [n, 3] by the volume's phase function at points of
    scenes s [n] (u [n, 3] uniform), and its weight p/pdf [n]: HG and its dual lobe drawn exactly,
    Mie's Cornette-Shanks through its HG, Rayleigh and isotropic uniformly."""
    from ..light.phase import henyey_greenstein

    kind, p = vol.params.phase.kind, vol.params.phase.value
    if kind == "hg" or kind == "mie":
        g = take(p.g, s)
    elif kind == "dual_hg":
        g = torch.where(u[:, 2] < take(p.weight, s), take(p.g_backward, s), take(p.g_forward, s))
    else:
        g = torch.zeros_like(u[:, 0])
    cos = hg_cos(g, u[:, 0])
    weight = torch.ones_like(cos)
    if kind in ("mie", "rayleigh"):  # not drawn exactly: the phase over the proposal's density
        proposal = henyey_greenstein(cos, g)
        weight = vol.phase.fn(p, cos, s) / proposal
    return _turn(d, cos, u[:, 1]), weight


def _by_volume(vols: list, vol: Tensor, fn: Callable[[object, Tensor], Tensor], like: Tensor) -> Tensor:
    """fn(volume state, rows) [m, ...] for the rows of each volume index in `vol` [n], put together
    [n, ...] (`like` gives the trailing shape and dtype)."""
    out = like.new_zeros(like.shape)
    for v, state in enumerate(vols):
        rows = (vol == v).nonzero().squeeze(1)
        if rows.numel():
            out[rows] = fn(state, rows)
    return out


def radiance(m: Media, lights: list, rays, background: Tensor | None, sky, *, bounces: int, samples: int,
             keys: Tensor) -> Tensor:
    """The path-traced radiance [n, 3] of camera `rays` [n]: the mean of `samples` paths a ray
    (`keys` [n, 3]: `geometry.sampling.ray_keys`), each of at most `bounces` scatterings, lit by
    `lights` (the render's `LightSource`s), seeing `background` [n, 3] (None: black) where the camera
    ray leaves the media and `sky(directions [m, 3], s [m]) -> [m, 3]` (None: black) where a
    scattered path does."""
    total = rays.origins.new_zeros(len(rays), 3)
    for k in range(samples):
        total = total + _trace(m, lights, rays, background, sky, bounces, Draws(path_keys(keys, k, samples), rays.origins.dtype))
    return total / samples


def _trace(m: Media, lights: list, rays, background, sky, bounces: int, draw: Draws) -> Tensor:
    """One path a ray [n, 3] (the module's estimator)."""
    s = rays.scene_index
    o, d = rays.origins.clone(), rays.directions.clone()
    beta, out = o.new_ones(o.shape[0], 3), o.new_zeros(o.shape[0], 3)
    ids = torch.arange(o.shape[0], device=o.device)
    for k in range(bounces + 1):
        t, vol, sigma, weight = _track(m, o[ids], d[ids], s[ids], torch.full_like(o[ids, 0], math.inf), draw, ids,
                                       collide=True)
        beta[ids] = beta[ids] * weight[:, None]
        left, ids, t, vol, sigma = _leave(out, beta, ids, vol < 0, t, vol, sigma)
        seen = (None if background is None else background[left]) if k == 0 else (
            None if sky is None else sky(d[left], s[left]))
        if seen is not None and left.numel():
            out[left] = out[left] + beta[left] * seen
        if not ids.numel():
            break
        x, si = o[ids] + t[:, None] * d[ids], s[ids]
        out[ids] = out[ids] + beta[ids] * _by_volume(m.vols, vol, lambda v, r: _emitted(v, x[r], si[r], sigma[r]), x)
        if k == bounces:
            break
        beta[ids] = beta[ids] * _by_volume(m.vols, vol, lambda v, r: take(v.params.albedo, si[r]), t)[:, None]
        out[ids] = out[ids] + beta[ids] * _next_event(m, lights, x, d[ids], si, vol, draw, ids)
        u = torch.stack([draw(ids) for _ in range(3)], dim=1)
        turned = _by_volume(m.vols, vol, lambda v, r: torch.cat(_sampled(v, d[ids[r]], si[r], u[r]), dim=1), x.new_zeros(len(ids), 4))
        o[ids], d[ids] = x, turned[:, :3]
        beta[ids] = beta[ids] * turned[:, 3:]
        if k + 1 >= ROULETTE_AFTER:
            ids = _roulette(beta, ids, draw)
    return out


def _leave(out: Tensor, beta: Tensor, ids: Tensor, gone: Tensor, t: Tensor, vol: Tensor, sigma: Tensor):
    """Splits paths `ids` [n] into those that left the media (`gone` [n]) and the others, with
    their t, volume and σ_t. -> (the paths that left, the others, their t, volume, σ_t)."""
    stay = ~gone
    return ids[gone], ids[stay], t[stay], vol[stay], sigma[stay]


def _sampled(vol, d: Tensor, s: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
    direction, weight = sample_phase(vol, d, s, u)
    return direction, weight[:, None]


def _emitted(vol, x: Tensor, s: Tensor, sigma: Tensor) -> Tensor:
    """What a real collision at x [m, 3] (σ_t `sigma` [m] there) in `vol` collects of its emission:
    σe/σ_t [m, 3], σe the physical march's emission source (emission · density, its emission map)."""
    from .emission import EMISSION_MAPS

    sigma_t = take(vol.params.sigma_t, s)
    density = sigma / sigma_t.clamp_min(torch.finfo(sigma.dtype).tiny)
    source = take(vol.params.emission, s) * density[:, None]
    if vol.plan.emission_map is not None:
        source = source + EMISSION_MAPS[vol.plan.emission_map].fn(vol.params.emission_map.value, x, density, s)
    return source / sigma.clamp_min(torch.finfo(sigma.dtype).tiny)[:, None]


def _next_event(m: Media, lights: list, x: Tensor, d: Tensor, s: Tensor, vol: Tensor, draw: Draws, ids: Tensor) -> Tensor:
    """Σ over `lights` of E · p(θ) · T towards the light [m, 3] at x [m, 3] of paths `ids` [m]
    arriving along d [m, 3] in volumes `vol` [m] (T ratio-tracked through every medium)."""
    out = x.new_zeros(x.shape[0], 3)
    for light in lights:
        toward = light.toward(x, s)
        cos = (d * toward.direction).sum(dim=1)
        phase = _by_volume(m.vols, vol, lambda v, r: v.phase.fn(v.params.phase.value, cos[r], s[r]), cos)
        through = transmittance(m, x, toward.direction, s, toward.distance, draw, ids)
        out = out + toward.irradiance * (phase * through)[:, None]
    return out


def _roulette(beta: Tensor, ids: Tensor, draw: Draws) -> Tensor:
    """Russian roulette: path i goes on with probability q = min(1, max |throughput|) (at least
    0.05), its throughput divided by q. -> the paths that go on."""
    q = beta[ids].abs().amax(dim=1).clamp(0.05, 1.0)
    on = draw(ids) < q
    kept = ids[on]
    beta[kept] = beta[kept] / q[on][:, None]
    return kept


__all__ = ["Draws", "Media", "PathCounts", "hg_cos", "majorant", "media", "path_keys", "radiance", "sample_phase", "transmittance"]
