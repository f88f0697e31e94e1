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

from ..noise import fast
from ..ops import lanes
from ..schema.batch import take

ROULETTE_AFTER = 3  # scatterings before Russian roulette may end a path
MARGIN = 1.5  # an estimated majorant: the largest lattice sample times this
LATTICE = 24  # samples a side of the lattice an estimated majorant comes from
MAX_TENTATIVE = 100_000  # tentative collisions a tracking call takes at most (then it stops: counted)
FADE = 0.05  # a ratio-tracked transmittance below this plays Russian roulette
_KEY, _DRAW = 0x7A17, 0x5CA7  # the hashes' seeds (already int32 values)


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
    kernel: bool = False  # the tracking as Dr.Jit kernels (`path_kernel`), else eagerly


def uniform_lanes(key, count):
    """Draw `count` of the paths of keys `key` (int32 lanes): a uniform value in [0, 1) from the
    top 24 bits of their hash (`noise.fast.hash_pair`), lanes (`ops.lanes`): eager and the kernel
    draw the same numbers."""
    return lanes.to_float((fast.hash_pair(key, count, _DRAW) >> 8) & 0xFFFFFF, _float_like(key)) * 2.0**-24


def _float_like(key):
    """A float lane of `key`'s backend (float32: both backends draw 24-bit values)."""
    return key.new_zeros((), dtype=torch.float32) if isinstance(key, Tensor) else 0.0


class Draws:
    """The eager tracer's draws: `uniform_lanes` for paths `ids` of keys `key` [n] (int32), each
    path's counter advanced per draw."""

    def __init__(self, key: Tensor, dtype: torch.dtype):
        self.key, self.count, self.dtype = key, torch.zeros_like(key), dtype

    def __call__(self, ids: Tensor) -> Tensor:
        u = uniform_lanes(self.key[ids], self.count[ids]).to(self.dtype)
        self.count.index_add_(0, ids, torch.ones_like(self.count[ids]))
        return u


def path_keys(keys: Tensor, sample: int, samples: int) -> Tensor:
    """Each ray's path key [n] (int32) for path `sample` of `samples`: the hash of its ray key [n, 3]
    (pixel column·spp + sub-sample, row, scene seed) with the sample."""
    k = keys.to(torch.int64)
    bits = lambda v: (torch.remainder(v + 2**31, 2**32) - 2**31).to(torch.int32)  # noqa: E731  its int32 bits
    return fast.hash32(bits(k[:, 0] * samples + sample), bits(k[:, 1]), bits(k[:, 2]), _KEY)


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


def media(vols: list, dtype: torch.dtype, *, kernel: bool = False) -> Media:
    """The paths' `Media` of the render's physically shaded volume states `vols` (`kernel`: their
    tracking in Dr.Jit kernels)."""
    return Media(vols, [majorant(v, dtype) for v in vols], kernel=kernel)


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


def track_lanes(o, d, t0: list, t1: list, total, sigma, key, count, *, collide: bool, steps: int) -> list:
    """Weighted delta tracking (`collide`) or ratio tracking along rays `o`, `d` (three lanes each)
    through volumes spanning [t0[v], t1[v]] (lanes a volume; empty: t0 = t1), their majorants
    summing to `total`, `sigma(v, x, mask)` volume v's σ_t at points x (three lanes) where `mask`
    (0 elsewhere), drawing `uniform_lanes(key, count)`: lanes (`ops.lanes`), the eager tracer's
    and the kernel's one source. -> [t of the real collision (inf: none), its volume (int, −1:
    none), its σ_t, the weight (the transmittance, ratio tracking), the counters after, whether a
    lane stopped at `steps` tentative collisions, its tentative collisions above the majorant, each
    volume's density evaluations]."""
    first, end = None, None
    for a, b in zip(t0, t1):
        entry = lanes.where(b > a, a, math.inf)
        first = entry if first is None else lanes.minimum(first, entry)
        end = b if end is None else lanes.maximum(end, b)
    t = lanes.where(total > 0.0, first, math.inf)
    none = count * 0 - 1

    def body(t, weight, hit, vol, sig_hit, count, live, n, above, *evals):
        u = uniform_lanes(key, count)
        count = count + lanes.to_int32(live)
        t = lanes.where(live, t - lanes.log(1.0 - u) / total, t)
        on = live & (t < end)
        x = [o[c] + t * d[c] for c in range(3)]
        masks = [on & (t >= t0[v]) & (t < t1[v]) for v in range(len(t0))]
        sig = [sigma(v, x, mask) for v, mask in enumerate(masks)]
        evals = [e + lanes.to_int32(mask) for e, mask in zip(evals, masks)]
        sig_sum = sum(sig[1:], sig[0])
        null = total - sig_sum
        above = above + lanes.to_int32(on & (null < 0.0))
        if not collide:  # the transmittance: a product of null fractions, faded out by roulette
            weight = lanes.where(on, weight * null / total, weight)
            low = on & (lanes.abs(weight) < FADE)
            u = uniform_lanes(key, count)
            count = count + lanes.to_int32(low)
            weight = lanes.where(low, lanes.where(u < 0.5, 2.0 * weight, 0.0), weight)
            return t, weight, hit, vol, sig_hit, count, on & (weight != 0.0), n + 1, above, *evals
        width = sig_sum + lanes.abs(null)  # σ_t + |σ_n|: σ̄ below the majorant
        u = uniform_lanes(key, count)
        count = count + lanes.to_int32(on)
        real = on & (u * width < sig_sum)
        weight = lanes.where(on, weight * lanes.where(real | (null >= 0.0), width, -width) / total, weight)
        pick = uniform_lanes(key, count) * sig_sum  # the volume: by its share of σ_t
        count = count + lanes.to_int32(real)
        k, chosen, acc = count * 0, sig[0], sig[0]
        for v in range(1, len(sig)):
            past = acc <= pick
            k, chosen, acc = lanes.where(past, v, k), lanes.where(past, sig[v], chosen), acc + sig[v]
        return (t, weight, lanes.where(real, t, hit), lanes.where(real, k, vol), lanes.where(real, chosen, sig_hit),
                count, on & ~real, n + 1, above, *evals)

    state = [t, lanes.full_like(t, 1.0), lanes.full_like(t, math.inf), none, lanes.full_like(t, 0.0), count, t < end,
             count * 0, count * 0] + [count * 0 for _ in t0]
    t, weight, hit, vol, sig_hit, count, live, n, above, *evals = lanes.while_loop(state, lambda *x: x[6] & (x[7] < steps), body)
    return [hit, vol, sig_hit, weight, count, live, above, *evals]


def _track(m: Media, o: Tensor, d: Tensor, s: Tensor, t_max: Tensor, draw: Draws, ids: Tensor, *, collide: bool):
    """`track_lanes` of rays o, d [n, 3] of scenes s [n] up to t_max [n] for paths `ids` [n] of
    `draw`: eagerly on torch columns, or as one Dr.Jit kernel (`m.kernel`). -> (t [n] of the real
    collision, inf: none; its volume [n] long, −1: none; its σ_t [n]; the weight [n])."""
    if o.shape[0] == 0:
        return t_max.clone(), torch.zeros_like(ids), t_max.clone(), t_max.clone()
    t0, t1, total = _intervals(m, o, d, s, t_max)
    if m.kernel:
        from .path_kernel import track_kernel

        hit, vol, sigma, weight, count, live, above, *_ = track_kernel(m, o, d, s, t0, t1, total, draw.key[ids], draw.count[ids],
                                                             collide=collide)
    else:
        x_of = lambda x, rows: torch.stack([c[rows] for c in x], dim=1)  # noqa: E731

        def sigma(v, x, mask):
            out, rows = x[0].new_zeros(x[0].shape), mask.nonzero().squeeze(1)
            if rows.numel():
                vol = m.vols[v]
                out[rows] = take(vol.params.sigma_t, s[rows]) * vol.field(x_of(x, rows), s[rows])
            return out

        hit, vol, sigma, weight, count, live, above, *_ = track_lanes(o.unbind(1), d.unbind(1), list(t0), list(t1), total, sigma,
                                                           draw.key[ids], draw.count[ids], collide=collide,
                                                           steps=MAX_TENTATIVE)
    draw.count[ids] = count
    m.counts.truncated += int(live.sum())
    m.counts.above_majorant += int(above.sum())
    return hit, vol.long(), sigma, weight


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
