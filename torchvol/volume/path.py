"""Path tracing of the physical media (`[path]`): every order of scattering, unbiased.

Each camera ray sends `[path].samples` paths. A path flies through every medium of the scene at
once by delta tracking against the media's majorants where it stands (their sum; a medium's from
its macro cells where its density kind bounds them, `local_majorant`), and at each real
collision collects the medium's emission (σe/σt), then, while it has scattered fewer than
`bounces` times, the light of every sun by next-event estimation (the phase function times the
light's irradiance times the transmittance towards it, by ratio tracking through every medium),
and scatters: its throughput times the albedo, a new direction drawn from the phase function.
Each point light it takes along each flight instead, at a point drawn ∝ 1/r² (`equiangular`).
Where the scene has an opaque surface (the terrain or the voxels, `Media.surface`, or the `[atmosphere]`'s
ground, whose air `air_media` adds as two media), it stops the flight and every shadow ray; a
path that meets it takes each light's a·E·cos θ and bounces cosine-weighted. A path that leaves
the media sees the sky. Russian roulette ends paths of low throughput past `ROULETTE_AFTER`
scatterings without bias. So `bounces = B` sums the light that scattered at most B times: B = 1
is the single-scattering integral the physical march computes; with `Media.marched_first` the
paths leave that integral to the march (`[path] single = "march"`).

Majorants (`majorant`): exact where the density has a known bound (constant, grid, exponential,
fbm), else the largest of a lattice of samples over the volume's box times `MARGIN`. Where a density
exceeds an estimated majorant, the tracking takes it at the majorant (a real collision for sure,
a null fraction of 0): biased there but never negative, and `stats["path"]["above_majorant"]`
counts those collisions, so a render that relied on it says so. (Weighted tracking, Kutz et al.
2017, stays unbiased with negative weights: it gave negative pixels in the fuzz, a cloudscape
shell whose 24³ lattice missed its clouds.)

Random numbers are a counter-based hash of (scene seed, pixel, sample, draw): a path's numbers
depend on nothing else, so a sample's bytes do not depend on the batch, chunking or threads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Callable

import torch
from torch import Tensor

from ..fields.base import torch_inputs
from ..geometry.rays import sphere_interval
from ..geometry.scatter import lambert_bounce, lambert_reflect, turn
from ..noise import fast
from ..ops import lanes
from ..schema.batch import take
from .density_lanes import inner_and_edge
from .emission import EMISSION_MAPS
from .local_majorant import bound_at, macro_cells, macro_lanes, macro_majorant
from .physical import sky_blend_weight

ROULETTE_AFTER = 3  # scatterings before Russian roulette may end a path
ROULETTE_SCALE = 4.0  # a path goes on with probability min(1, this × its throughput) (tools/bench_path.py)
MARGIN = 1.5  # an estimated majorant: the largest lattice sample times this
LATTICE = 24  # samples a side of the lattice an estimated majorant comes from
MAX_TENTATIVE = 100_000  # steps (tentative collisions, moves past a local majorant) a tracking call takes at most (then it stops: counted)
FADE = 0.05  # a ratio-tracked transmittance below this plays Russian roulette
LOCAL_MAJORANTS = True  # media tracked against their macro cells' bounds where their kind gives them (`local_majorant`); False: one
PATH_LANES = 1 << 18  # paths traced as one batch: the samples of a chunk's rays are grouped up to this
SUN_FLIGHTS = True  # the suns' next events by a flight of their own (`_suns_next`); False: plain, the tests' reference
_KEY, _DRAW = 0x7A17, 0x5CA7  # the hashes' seeds (already int32 values)


@dataclass
class PathCounts:
    """What a render's paths did: collisions above a majorant, trackings cut at MAX_TENTATIVE."""

    above_majorant: int = 0
    truncated: int = 0


@dataclass
class Media:
    """The physically shaded volumes a path meets (`vols`, the render's volume states), each
    one's majorant of σ_t per scene (`majorants` (B,)), the render's counts, the scene's opaque
    surface or None: `surface(s [n], per_ray, like [n], kernel)` -> its lanes for rays of scenes s
    (`terrain.path_surface`'s, `voxel.path_surface`'s: hit -> (t, facts), normal(x, facts),
    albedo(n, facts), emitted(facts) or None, lift(x, n, t, facts), visible, reflect(facts, n,
    view, light) -> three lanes (π·BRDF·cos over the albedo: `lambert_reflect`), bounce(facts, n,
    d, u) -> (direction, three weights) (`lambert_bounce`);
    several as one: `surfaces`), and its `[atmosphere]`
    (`air_media`: two more media and the planet's ground as the surface) or None."""

    vols: list
    majorants: list[Tensor]
    counts: PathCounts = field(default_factory=PathCounts)
    surface: Callable | None = None
    air: object | None = None  # the batch's `[atmosphere]` (Stacked) or None: `air_media`
    marched_first: bool = False  # `[path] single = "march"`: the paths leave out what the march gives
    local: list | None = None  # each volume's `local_majorant.MacroMajorant` or None (None: none has them)


def uniform_lanes(key, count):
    """Draw `count` of the paths of keys `key` (int32 lanes): a uniform value in [0, 1) from the
    top 24 bits of their hash (`noise.fast.hash_pair`), lanes (`ops.lanes`): eager and the kernel
    draw the same numbers."""
    return lanes.to_float((fast.hash_pair(key, count, _DRAW) >> 8) & 0xFFFFFF, _float_like(key)) * 2.0**-24


def _float_like(key):
    """A float lane of `key`'s backend (float32: both backends draw 24-bit values)."""
    return key.new_zeros((), dtype=torch.float32) if isinstance(key, Tensor) else 0.0


def path_keys(keys: Tensor, sample: int, samples: int) -> Tensor:
    """Each ray's path key [n] (int32) for path `sample` of `samples`: its ray key [n, 3] (pixel
    column·spp + sub-sample, row, scene seed) hashed, then hashed with the sample under a seed of
    the sample count, so renders of different sample counts draw independent paths (a reference
    ladder's rungs, `measure.reference`)."""
    k = keys.to(torch.int64)
    bits = lambda v: (torch.remainder(v + 2**31, 2**32) - 2**31).to(torch.int32)  # noqa: E731  its int32 bits
    ray = fast.hash32(bits(k[:, 0]), bits(k[:, 1]), bits(k[:, 2]), _KEY)
    return fast.hash_pair(ray, sample, int(bits(torch.tensor(_KEY + samples * 0x9E3779B1))))


def majorant(vol, dtype: torch.dtype) -> Tensor:
    """An upper bound (B,) of the volume's σ_t over its bounds (`density_bound` times σ_t)."""
    return vol.params.sigma_t.to(dtype) * density_bound(vol, dtype)


def density_bound(vol, dtype: torch.dtype) -> Tensor:
    """An upper bound (B,) of the volume's density over its bounds: exact for constant, grid and
    exponential densities and for a density kind that declares one (`DENSITIES`' ``bound``: fbm,
    cloudscape); else `MARGIN` × the largest σ_t on a `LATTICE`³ lattice of its box, and where a
    kind declares a bound and has a box, the lower of the two, the declared one where the lattice
    saw no density at all (a thin layer in a wide box: a cloudscape shell's 24³ lattice missed its
    clouds, and a majorant of 0 tracks nothing, with no collision above it to count)."""
    from ..fields import DENSITIES

    p, kind = vol.params, vol.params.density.kind
    inner = inner_and_edge(vol)[0]  # an edge fade only lowers the density
    declared = DENSITIES[kind].caps.get("bound")
    if kind == "constant":
        bound = p.density.value.to(dtype)
    elif kind == "grid":
        bound = torch.stack([g.max() for g in inner.grids]).to(dtype)
    elif kind == "exponential":
        e = p.density.value
        low = vol.bounds.caps["height_range"](p.bounds.value)[:, 0].to(dtype)
        bound = e.value.to(dtype) * torch.exp(((e.base - low) / e.scale_height).clamp(max=math.log(1e12)))
    elif vol.bounds.caps["aabb"] is None and declared is not None:
        bound = declared(p.density.value).to(dtype).clamp_min(0.0)
    else:
        seen = _lattice_maximum(vol, dtype) * MARGIN
        if declared is None:
            bound = seen
        else:
            known = declared(p.density.value).to(seen).clamp_min(0.0)
            bound = torch.where(seen > 0, torch.minimum(known, seen), known)
    return bound.clamp(max=1e12)


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


def media(vols: list, dtype: torch.dtype, surface: Callable | None = None, air=None, *, marched_first: bool = False) -> Media:
    """The paths' `Media` of the render's physically shaded volume states `vols`, its opaque
    `surface` (`Media.surface`) or None, its `[atmosphere]` (Stacked) or None, and whether the
    march gives the single scattering (`Media.marched_first`)."""
    bounds = [density_bound(v, dtype) for v in vols]
    return Media(vols, [v.params.sigma_t.to(dtype) * bound for v, bound in zip(vols, bounds)], surface=surface, air=air,
                 marched_first=marched_first, local=[_local(v, bound, dtype) for v, bound in zip(vols, bounds)])


def _local(vol, bound: Tensor, dtype: torch.dtype):
    """The volume's local majorants (`local_majorant`) where its density kind gives macro cells'
    bounds (`DENSITIES`' ``macro``: grids, value-noise fbm, exponential profiles; media with a box)
    and `LOCAL_MAJORANTS`, else None: one majorant over its bounds. `bound` (B,): its one bound of
    the density (`density_bound`), which no local one passes (an estimated one, a lattice's, may be
    the lower)."""
    from ..fields import DENSITIES

    macro, aabb = DENSITIES[vol.params.density.kind].caps.get("macro"), vol.bounds.caps["aabb"]
    if not LOCAL_MAJORANTS or macro is None or aabb is None:
        return None
    field = inner_and_edge(vol)[0]
    low, high = (x.to(torch.float64) for x in aabb(vol.params.bounds.value))
    cells = macro_cells(vol.params.sigma_t.to(torch.float64) * bound.to(torch.float64), low, high)
    parts = [macro(field, b, low[b], high[b], cells[b]) for b in range(low.shape[0])]
    if any(part is None for part in parts):
        return None
    return macro_majorant([(part[0].clamp(max=float(bound[b])).to(dtype), *(x.to(dtype) for x in part[1:]))
                           for b, part in enumerate(parts)])


def hero_channels(keys: Tensor, sample: int) -> Tensor:
    """Each ray's colour [n] (int32 0, 1, 2) for its path `sample`, where a medium's extinction
    differs per colour (the air's Rayleigh): the path tracks that colour's σ alone and counts its
    radiance three times in that colour (`trace_lanes`), unbiased. Stratified: a ray's colours
    cycle from a start hashed from its key [n, 3], so any three consecutive samples take each
    colour once (drawn independently, a pixel's colours came out unequal: noise in hue)."""
    start = torch.remainder(path_keys(keys, 0, 1).to(torch.int64), 3)
    return ((start + sample) % 3).to(torch.int32)


def air_media(layer, per_ray, channel) -> tuple[list, SimpleNamespace]:
    """The `[atmosphere]` (`layer`, the batch's Stacked table) as media and surface of the paths
    (`per_ray`: per scene -> lanes; `channel`: each path's colour, `hero_channels`), in the scene's
    frame (ground y = 0, the planet's centre (0, −R, 0)): Rayleigh (albedo 1, its σ of the path's
    colour, its phase) and Mie (extinction `MIE_EXTINCTION` × its scattering, Cornette-Shanks,
    drawn through the HG of its g) with the march's exponential densities (`density_lanes`, at
    most 1: the majorant is the ground's σ), and the planet's ground, a Lambertian sphere (the
    march's albedo/π: `direct`) that stops flights and shadow rays."""
    from ..light.atmosphere import (
        MIE_EXTINCTION,
        density_lanes,
        falloff_rates,
        ground_distance_lanes,
    )
    from ..light.phase import mie_cornette_shanks, rayleigh

    radius, top = per_ray(layer.planet_radius), per_ray(layer.planet_radius + layer.atmosphere_height)
    q = SimpleNamespace(planet_radius=radius, falloff=[per_ray(falloff_rates(h)) for h in (layer.rayleigh_height, layer.mie_height)])
    frame = lambda x: [x[0], x[1] + radius, x[2]]  # noqa: E731  the planet's frame
    colours = per_ray(layer.rayleigh)
    sigmas = [_pick(channel, colours), MIE_EXTINCTION * per_ray(layer.mie)]
    g, ground = per_ray(layer.mie_g), per_ray(layer.ground)

    def medium(k, albedo, phase, lobe):
        def sigma(x, mask):
            return lanes.where(mask, sigmas[k] * density_lanes(frame(x), q)[k], 0.0)

        return SimpleNamespace(interval=lambda o, d: sphere_interval(frame(o), d, (0.0, 0.0, 0.0), top), reach=3e38,
                               majorant=sigmas[k], local=None, sigma_t=sigmas[k], albedo=albedo, emission=[0.0] * 3, glow=None,
                               lobe=lobe, weighted=True, phase=phase, sigma=sigma, blend=None)

    air = [medium(0, 1.0, rayleigh, (0.0, 0.0, 0.0)), medium(1, 1.0 / MIE_EXTINCTION, lambda c: mie_cornette_shanks(c, g), (g, g, 0.0))]

    def normal(x):
        p = frame(x)
        length = lanes.length3(*p)
        return [c / length for c in p]

    blocked = lambda p, direction, distance: ground_distance_lanes(p, direction, radius) < distance  # noqa: E731
    surface = SimpleNamespace(hit=lambda o, d, t_max: (ground_distance_lanes(o, d, radius), []),
                              normal=lambda x, facts: normal(x), albedo=lambda n, facts: ground, emitted=None,
                              reflect=lambert_reflect(1.0 / math.pi), bounce=lambert_bounce,
                              lift=lambda x, n, t, facts: [x[c] + (1e-4 * (1.0 + t)) * n[c] for c in range(3)],
                              visible=lambda p, direction, distance: lanes.where(blocked(p, direction, distance), 0.0, 1.0))
    return air, surface


def surfaces(a: SimpleNamespace, b: SimpleNamespace, *, over: bool = False) -> SimpleNamespace:
    """Two opaque surfaces of the paths as one (`Media.surface`'s lanes): a ray meets the nearer
    (`over`: `a` wherever it meets `a`, as the march puts a scene's surface over the planet's
    ground), its facts saying which and holding both's; a shadow ray must pass both."""
    def hit(o: list, d: list, t_max):
        ta, fa = a.hit(o, d, t_max)
        tb, fb = b.hit(o, d, t_max if over else lanes.minimum(ta, t_max))  # b's walk ends at a's hit
        first = (ta < math.inf) if over else (ta <= tb)
        return lanes.where(first, ta, tb), (first, fa, fb)

    def either(f, x, y) -> list:  # three lanes each, `a`'s where it was met
        return [lanes.where(f[0], p, q) for p, q in zip(x, y)]

    def emitted(f) -> list:
        return either(f, *([0.0] * 3 if s.emitted is None else s.emitted(g) for s, g in ((a, f[1]), (b, f[2]))))

    return SimpleNamespace(hit=hit, normal=lambda x, f: either(f, a.normal(x, f[1]), b.normal(x, f[2])),
                           albedo=lambda n, f: either(f, a.albedo(n, f[1]), b.albedo(n, f[2])),
                           emitted=None if a.emitted is None and b.emitted is None else emitted,
                           lift=lambda x, n, t, f: either(f, a.lift(x, n, t, f[1]), b.lift(x, n, t, f[2])),
                           visible=lambda p, d, dist: a.visible(p, d, dist) * b.visible(p, d, dist),
                           reflect=lambda f, n, v, l: either(f, a.reflect(f[1], n, v, l), b.reflect(f[2], n, v, l)),
                           bounce=lambda f, n, d, u: _either_bounce(f, a.bounce(f[1], n, d, u), b.bounce(f[2], n, d, u)))


def _either_bounce(f, x: tuple, y: tuple) -> tuple:
    """`surfaces`' bounce: (direction, weight) of `a` where it was met, else of `b`."""
    pick = lambda p, q: [lanes.where(f[0], i, j) for i, j in zip(p, q)]  # noqa: E731
    return pick(x[0], y[0]), pick(x[1], y[1])


def with_air(q: SimpleNamespace, m: Media, channel, per_ray) -> SimpleNamespace:
    """`q` (`path_inputs`, its `sigma`) with the scene's `[atmosphere]` added where it has one: the
    air's media after the volumes, the ground as a surface (under the scene's own), each path's
    colour `channel` (int lanes, `hero_channels`)."""
    if m.air is None:
        if not m.vols:  # (`path_inputs`' vacuum)
            q.sigma = lambda v, x, mask: q.vols[v].sigma(x, mask)
        return q
    q.channel = channel
    air, ground = air_media(m.air, per_ray, channel)
    q.surface = ground if q.surface is None else surfaces(q.surface, ground, over=True)
    first, own = len(q.vols), q.sigma
    q.vols = q.vols + air
    q.sigma = lambda v, x, mask: own(v, x, mask) if v < first else q.vols[v].sigma(x, mask)
    return q


def track_lanes(o, d, t0: list, t1: list, total, q, key, count, *, collide: bool, steps: int) -> list:
    """Delta tracking (`collide`) or ratio tracking along rays `o`, `d` (three lanes each)
    through volumes spanning [t0[v], t1[v]] (lanes a volume; empty: t0 = t1), their majorants
    summing to `total` (0: nothing to track), `q` the volumes (`path_inputs`: each one's majorant
    and local majorants, `q.sigma(v, x, mask)` its σ_t at points x (three lanes) where `mask`, 0
    elsewhere), drawing `uniform_lanes(key, count)`: lanes (`ops.lanes`), the eager tracer's and
    the kernel's one source. Each step draws a free flight against the majorant where the ray
    stands (`_majorant_at`); a flight past where that majorant holds moves there without a
    collision (an exponential restarts anywhere: tracking against a piecewise-constant majorant).
    -> [t of the real collision (inf: none), its volume (int, −1: none), its σ_t, the weight (the
    transmittance, ratio tracking), the counters after, whether a lane stopped at `steps` steps,
    its tentative collisions above the majorant, each volume's density evaluations]."""
    first, end = _extent(t0, t1)
    t = lanes.where(total > 0.0, first, math.inf)
    none = count * 0 - 1

    def body(t, weight, hit, vol, sig_hit, count, live, n, above, *evals):
        u = uniform_lanes(key, count)
        count = count + lanes.to_int32(live)
        bound, reach = _majorant_at(q, [o[c] + t * d[c] for c in range(3)], d, t, t0, t1)
        flight = lanes.where(bound > 0.0, -lanes.log(1.0 - u) / bound, math.inf)
        passed = flight >= reach
        # a move past the reach is at least a float32 step of t (far out, t + reach could round to t)
        t = lanes.where(live, t + lanes.where(passed, lanes.maximum(reach, lanes.abs(t) * 2.0**-22), flight), t)
        going = live & (t < end)
        on = going & ~passed
        x = [o[c] + t * d[c] for c in range(3)]
        masks = [on & (t >= t0[v]) & (t < t1[v]) for v in range(len(t0))]
        sig = [q.sigma(v, x, mask) for v, mask in enumerate(masks)]
        evals = [e + lanes.to_int32(mask) for e, mask in zip(evals, masks)]
        sig_sum = sum(sig[1:], sig[0])
        null = bound - sig_sum
        above = above + lanes.to_int32(on & (null < 0.0))
        if not collide:  # the transmittance: a product of null fractions, faded out by roulette
            weight = lanes.where(on, weight * lanes.clamp_min(null, 0.0) / bound, weight)  # 0 above the majorant
            low = on & (weight < FADE)
            u = uniform_lanes(key, count)
            count = count + lanes.to_int32(low)
            weight = lanes.where(low, lanes.where(u < 0.5, 2.0 * weight, 0.0), weight)
            return t, weight, hit, vol, sig_hit, count, going & (weight != 0.0), n + 1, above, *evals
        u = uniform_lanes(key, count)
        count = count + lanes.to_int32(on)
        real = on & (u * bound < sig_sum)  # for sure above the majorant
        pick = uniform_lanes(key, count) * sig_sum  # the volume: by its share of σ_t
        count = count + lanes.to_int32(real)
        k, chosen, acc = count * 0, sig[0], sig[0]
        for v in range(1, len(sig)):
            past = acc <= pick
            k, chosen, acc = lanes.where(past, v, k), lanes.where(past, sig[v], chosen), acc + sig[v]
        return (t, weight, lanes.where(real, t, hit), lanes.where(real, k, vol), lanes.where(real, chosen, sig_hit),
                count, going & ~real, n + 1, above, *evals)

    state = [t, lanes.full_like(t, 1.0), lanes.full_like(t, math.inf), none, lanes.full_like(t, 0.0), count, t < end,
             count * 0, count * 0] + [count * 0 for _ in t0]
    t, weight, hit, vol, sig_hit, count, live, n, above, *evals = lanes.while_loop(state, lambda *x: x[6] & (x[7] < steps), body)
    return [hit, vol, sig_hit, weight, count, live, above, *evals]


def _majorant_at(q, x: list, d: list, t, t0: list, t1: list) -> tuple:
    """The majorant summed over the volumes at t along rays of directions d (x their points there,
    three lanes each) and how far on it holds: a volume's within its span [t0[v], t1[v]], up to the span's end,
    the next span's start or its local majorant's reach; its local majorant where it has them
    (`local_majorant`), else its one. Lanes."""
    bound, reach = lanes.full_like(t, 0.0), lanes.full_like(t, math.inf)
    for v, vol in enumerate(q.vols):
        inside = (t >= t0[v]) & (t < t1[v])
        here, far = vol.majorant, t1[v] - t
        if vol.local is not None:
            here, holds = vol.local(x, d)
            far = lanes.minimum(far, holds)
        bound = bound + lanes.where(inside, here, 0.0)
        reach = lanes.minimum(reach, lanes.where(t < t0[v], t0[v] - t, lanes.where(inside, far, math.inf)))
    return bound, reach


def _extent(t0: list, t1: list):
    """Where rays first enter any of the volumes spanning [t0[v], t1[v]] (lanes; inf: none) and
    where they last leave one."""
    first, end = None, None
    for a, b in zip(t0, t1):
        entry = lanes.where(b > a, a, math.inf)
        first = entry if first is None else lanes.minimum(first, entry)
        end = b if end is None else lanes.maximum(end, b)
    return first, end


def hg_cos(g, u):
    """cos θ drawn from Henyey-Greenstein g by inverting its CDF at u (|g| < 1e-3: isotropic), lanes."""
    small = lanes.abs(g) < 1e-3
    gs = lanes.where(small, 1.0, g)
    q = (1.0 - gs * gs) / (1.0 - gs + 2.0 * gs * u)
    return lanes.clamp(lanes.where(small, 1.0 - 2.0 * u, (1.0 + gs * gs - q * q) / (2.0 * gs)), -1.0, 1.0)


def _pick(vol, values: list):
    """values[vol] per lane (`vol` int lanes, −1 or out of range: values[0]), lanes."""
    out = values[0]
    for v in range(1, len(values)):
        out = lanes.where(vol == v, values[v], out)
    return out


def _phase_sample(q, vol, d: list, u: list):
    """A direction scattered from d by the phase function of each lane's volume (u three uniform
    lanes) and its weight p/pdf: HG and its dual lobe drawn exactly, Mie through its HG, Rayleigh
    and isotropic uniformly."""
    cos = _drawn_cos(q, vol, u[0], u[2])
    weight = _pick(vol, [m.phase(cos) / _drawn_density(m, cos) if m.weighted else lanes.full_like(cos, 1.0) for m in q.vols])
    return turn(d, cos, u[1]), weight


def _drawn_cos(q, vol, u, u_lobe):
    """cos θ drawn from each lane's volume's phase sampler (`_phase_sample`) at uniform lanes u,
    its dual lobe picked by `u_lobe`."""
    return hg_cos(_pick(vol, [lanes.where(u_lobe < m.lobe[2], m.lobe[1], m.lobe[0]) for m in q.vols]), u)


def _drawn_density(m, cos):
    """The density over directions of medium m's phase sampler at cos θ: the phase function where it
    is drawn exactly (HG, its dual lobe, isotropic), else the HG of its g it is drawn through."""
    from ..light.phase import henyey_greenstein

    return henyey_greenstein(cos, m.lobe[0]) if m.weighted else m.phase(cos)


def _spans(q, o: list, d: list, alive, t_max=None):
    """Each volume's span [t0, t1] along rays o, d (empty: t0 = t1 = 0; not `alive`: empty) up to
    t_max (None: no limit) and the majorants summed over the volumes crossed, lanes."""
    t0, t1, total = [], [], lanes.full_like(o[0], 0.0)
    for m in q.vols:
        near, far = m.interval(o, d)
        a = lanes.clamp_min(near, 0.0)
        b = lanes.minimum(far, m.reach if t_max is None else lanes.minimum(t_max, m.reach))
        crosses = alive & (b > a)
        t0.append(lanes.where(crosses, a, 0.0))
        t1.append(lanes.where(crosses, b, 0.0))
        total = total + lanes.where(crosses, m.majorant, 0.0)
    return t0, t1, total


def trace_lanes(q, o: list, d: list, key, *, bounces: int, marched_first: bool = False) -> list:
    """One path a lane from o along d (three lanes each; `key` int32 lanes), the module's
    estimator, lanes (`ops.lanes`): eagerly on torch columns, as one Dr.Jit kernel in
    `path_kernel`. `q` (`path_inputs`): the volumes (their interval, reach, majorant, σ_t,
    albedo, emission, phase), the lights, per lane, and the opaque surface (`Media.surface`'s
    lanes) or None. `marched_first`: what the march gives is left out: the light of the lights
    and the emission at a path's first collision, and (in `radiance`) the camera ray's
    background. -> [radiance (3), throughput (3) and
    direction (3) where it left the media, whether it left, its scatterings, tentative collisions
    past the step limit and above a majorant, each volume's density evaluations]."""
    one = lanes.full_like(o[0], 1.0)
    zero_i, alive = key * 0, one > 0.0
    V = len(q.vols)

    def body(*state):
        o, d, beta, out = list(state[0:3]), list(state[3:6]), list(state[6:9]), list(state[9:12])
        count, k, alive, gone, guided, *tally = state[12:]
        # the surface's hit t (inf: none); a finished path's walk ends at once (t_max 0)
        wall, facts = (None, None) if q.surface is None else q.surface.hit(o, d, lanes.where(alive, math.inf, 0.0))
        later = k > 0 if marched_first else alive  # the scatterings the paths add light from
        t0, t1, total = _spans(q, o, d, alive, wall)
        out, count, tally = _lights_along(q, o, d, (t0, t1), alive & (k < bounces) & later, alive & (k == 0), beta, out,
                                          key, count, tally)
        hit, vol, sig, w, count, live, extra, *ev = track_lanes(o, d, t0, t1, total, q, key, count,
                                                                collide=True, steps=MAX_TENTATIVE)
        tally = _tallied(tally, live, extra, ev)
        beta = [lanes.where(alive, b * w, b) for b in beta]
        left = alive & (vol < 0)
        face = None if wall is None else left & (wall < math.inf)  # a path that met the surface bounces off it
        left = left if face is None else left & ~face
        gone, alive = gone | left, alive & ~left
        t = lanes.where(alive, hit if face is None else lanes.where(face, wall, hit), 0.0)
        x = [o[c] + t * d[c] for c in range(3)]
        beta, out = _blended(q, vol, t, alive & (k == 0) if face is None else alive & (k == 0) & ~face, later, beta, out)
        emitted = _emitted(q, vol, x, sig)
        lit = (alive if face is None else alive & ~face) & later
        out = [lanes.where(lit, out[c] + beta[c] * emitted[c], out[c]) for c in range(3)]
        if face is not None and q.surface.emitted is not None:  # an emitting surface (the voxels' materials)
            glow, lit = q.surface.emitted(facts), alive & face & later
            out = [lanes.where(lit, out[c] + beta[c] * glow[c], out[c]) for c in range(3)]
        alive = alive & (k < bounces)
        albedo, normal, x = _collision(q, vol, x, face, wall, facts)
        beta = [lanes.where(alive, b * a, b) for b, a in zip(beta, albedo)]
        out, count, tally = _lights_at(q, x, d, vol, alive & later, face, normal, facts, beta, out, key, count, tally,
                                       taken=guided)
        medium = alive if face is None else alive & ~face
        out, count, tally, guided = _suns_next(q, x, d, vol, medium & (k + 1 < bounces), beta, out, key, count, tally)
        turned, weight, count = _scatter(q, vol, d, face, normal, facts, key, count, alive)
        d = [lanes.where(alive, turned[c], d[c]) for c in range(3)]
        beta = [lanes.where(alive, b * w, b) for b, w in zip(beta, weight)]
        o = [lanes.where(alive, x[c], o[c]) for c in range(3)]
        k = k + lanes.to_int32(alive)
        beta, alive, count = _roulette(beta, alive & (k >= ROULETTE_AFTER), alive, key, count)
        return (*o, *d, *beta, *out, count, k, alive, gone, guided, *tally)

    state = [*o, *d, one, one, one, one * 0.0, one * 0.0, one * 0.0, zero_i, zero_i, alive, ~alive, ~alive, zero_i, zero_i]
    state = lanes.while_loop(state + [zero_i] * V, lambda *x: x[14], body)
    out, beta = _in_channel(q.channel, state[9:12]), _in_channel(q.channel, state[6:9])
    return [*out, *beta, *state[3:6], state[15], state[13], state[17], state[18], *state[19:]]


def _in_channel(channel, values: list) -> list:
    """Three lanes as a path of colour `channel` (`hero_channels`) counts them: 3× in its colour,
    0 in the others (None: all colours tracked, as they are)."""
    if channel is None:
        return values
    return [v * lanes.where(channel == c, 3.0, 0.0) for c, v in enumerate(values)]


def _tallied(tally: list, live, extra, evals: list) -> list:
    """The path's counters [trackings cut, tentative collisions above a majorant, each volume's
    density evaluations] after a tracking (`track_lanes`'s `live`, its above-majorant count and
    evaluations)."""
    cut, above, *before = tally
    return [cut + lanes.to_int32(live), above + extra, *[a + b for a, b in zip(before, evals)]]


def _shadow(q, x: list, direction: list, distance, on, key, count, tally, *, occluded: bool = True):
    """The transmittance from x (three lanes) along `direction` up to `distance` through every
    medium, ratio-tracked, times the surface's visibility (where the scene has one and the ray
    may be `occluded`), where `on` (else 0). -> (it, the counters, the tally)."""
    s0, s1, tot = _spans(q, x, direction, on, distance)
    _, _, _, through, count, live, extra, *ev = track_lanes(x, direction, s0, s1, tot, q, key, count,
                                                            collide=False, steps=MAX_TENTATIVE)
    if q.surface is not None and occluded:  # (a ray not `on` ends its walk at once: distance 0)
        through = through * lanes.where(on, q.surface.visible(x, direction, lanes.where(on, distance, 0.0)), 0.0)
    return through, count, _tallied(tally, live, extra, ev)


def _lights_at(q, x: list, d: list, vol, alive, face, normal, facts, beta: list, out: list, key, count, tally, *, taken):
    """Next-event estimation at the collisions x (three lanes) of paths flying along d: each sun's
    E·p(θ)·T in a medium (its phase function; not where the collision before `taken` it,
    `_suns_next`) or a·E·cos θ·T on the surface (`face`; the albedo already in `beta`); a point
    light's only on the surface (in the media `_lights_along` takes it). -> (the radiance `out`
    plus it, the counters, the tally)."""
    medium = taken if face is None else taken & ~face
    for light in q.lights:
        at = alive & ~medium if light.position is None else (None if face is None else alive & face)
        if at is None:
            continue
        direction, irradiance, distance = light.toward(x)
        cos = lanes.dot3(d, direction)
        phase = [_pick(vol, [m.phase(cos) for m in q.vols])] * 3
        if face is not None:  # the surface's reflectance towards where the path came from
            reflected = q.surface.reflect(facts, normal, [-c for c in d], direction)
            phase = [lanes.where(face, r, p) for r, p in zip(reflected, phase)]
        through, count, tally = _shadow(q, x, direction, distance, at, key, count, tally)
        out = [lanes.where(at, out[c] + beta[c] * irradiance[c] * (phase[c] * through), out[c]) for c in range(3)]
    return out, count, tally


def _suns_next(q, x: list, d: list, vol, on, beta: list, out: list, key, count, tally):
    """The suns' next events of the collision after x (three lanes; in a medium, where `on`), for
    paths flying along d whose throughput there is `beta`: a flight of its own from x whose
    direction d' is drawn from a mixture of the phase function about d and its lobe about each
    sun, weighted p(d·d')/pdf(d'); where it collides in a medium, the suns' E·p(θ)·T there. The
    path's own next collision leaves them out (`_lights_at`'s `taken`). Unbiased as the next
    event it replaces; the phase function's forward peak, which a next event meets only where the
    path happened to fly towards a sun (HG 0.8: 45× its mean, a next event's relative deviation
    3.4), is drawn where it lies (`SUN_FLIGHTS`). -> (out plus it, the counters, the tally, where
    the path's next collision leaves them out)."""
    suns = [light for light in q.lights if light.position is None]
    if not suns or not SUN_FLIGHTS:
        return out, count, tally, on & False
    u = []
    for _ in range(4):
        u.append(uniform_lanes(key, count))
        count = count + lanes.to_int32(on)
    towards = [sun.toward(x)[0] for sun in suns]
    axis = d
    for i, direction in enumerate(towards):  # the lobe about sun i where 0.5 + i/(2S) <= u0 < ...
        axis = [lanes.where(u[0] >= 0.5 + 0.5 * i / len(suns), a, b) for a, b in zip(direction, axis)]
    flight = turn(axis, _drawn_cos(q, vol, u[1], u[3]), u[2])
    own = lambda c: _pick(vol, [_drawn_density(m, c) for m in q.vols])  # noqa: E731
    pdf = 0.5 * own(lanes.dot3(d, flight)) + sum(own(lanes.dot3(flight, t)) for t in towards) * (0.5 / len(suns))
    weight = _pick(vol, [m.phase(lanes.dot3(d, flight)) for m in q.vols]) / lanes.clamp_min(pdf, 1e-30)
    t0, t1, total = _spans(q, x, flight, on)
    hit, vol2, _, _, count, live, extra, *ev = track_lanes(x, flight, t0, t1, total, q, key, count, collide=True,
                                                           steps=MAX_TENTATIVE)
    tally = _tallied(tally, live, extra, ev)
    at = on & (vol2 >= 0)
    y = [x[c] + lanes.where(at, hit, 0.0) * flight[c] for c in range(3)]
    if q.surface is not None:
        at = at & (q.surface.visible(x, flight, lanes.where(at, hit, 0.0)) > 0.0)
    gain = weight * _pick(vol2, [m.albedo for m in q.vols])
    for sun in suns:
        direction, irradiance, distance = sun.toward(y)
        phase = _pick(vol2, [m.phase(lanes.dot3(flight, direction)) for m in q.vols])
        through, count, tally = _shadow(q, y, direction, distance, at, key, count, tally)
        out = [lanes.where(at, out[c] + beta[c] * irradiance[c] * (gain * phase * through), out[c]) for c in range(3)]
    return out, count, tally, on


def _lights_along(q, o: list, d: list, spans: tuple, on, camera, beta: list, out: list, key, count, tally):
    """Each point light's single scattering along the whole flight from o along d (three lanes
    each) where `on`: one point y of the media's span drawn ∝ 1/r² to the light (`equiangular`),
    Σ σ_s·p(θ) there times I/r², the transmittance o→y and y→light, over its density. Its 1/r²
    peak makes a collision's next event (`_lights_at`) a heavy-tailed estimate near the light,
    infinite variance inside a medium; this one is bounded. `spans`: each volume's (t0, t1) along
    the flight (`_spans`); `camera`: the flight is the camera ray's (where a volume's sky blend
    takes its share, `_blended`). -> (out plus it, the counters, the tally)."""
    points = [light for light in q.lights if light.position is not None]
    if not points:
        return out, count, tally
    t0, t1 = spans
    start, end = _extent(t0, t1)
    at = on & (end > start)
    for light in points:
        u = uniform_lanes(key, count)
        count = count + lanes.to_int32(at)
        t, density = equiangular(o, d, light.position, lanes.where(at, start, 0.0), lanes.where(at, end, 1.0), u)
        y = [o[c] + t * d[c] for c in range(3)]
        direction, irradiance, distance = light.toward(y)
        cos = lanes.dot3(d, direction)
        masks = [at & (t >= a) & (t < b) for a, b in zip(t0, t1)]
        scatter = None
        for v, (m, mask) in enumerate(zip(q.vols, masks)):
            term = m.albedo * q.sigma(v, y, mask) * m.phase(cos)
            if m.blend is not None:
                term = term * lanes.where(camera, 1.0 - sky_blend_weight(m.blend, t), 1.0)
            scatter = term if scatter is None else scatter + term
        tally = tally[:2] + [e + lanes.to_int32(mask) for e, mask in zip(tally[2:], masks)]
        before, count, tally = _shadow(q, o, d, t, at, key, count, tally, occluded=False)  # (y is short of the surface)
        after, count, tally = _shadow(q, y, direction, distance, at, key, count, tally)
        weight = scatter * before * after / density
        out = [lanes.where(at, out[c] + beta[c] * irradiance[c] * weight, out[c]) for c in range(3)]
    return out, count, tally


def equiangular(o: list, d: list, c: list, start, end, u):
    """A distance t in [start, end] along rays o, d (three lanes each, d unit) drawn with density
    ∝ 1/r², r the distance to the point c (Kulla & Fajardo 2012: uniform in the angle the ray
    subtends at c), at uniform lanes u, and that density. The ray's distance to c is taken at least
    `POINT_RADIUS` (the lights' own floor under r), so a ray through the light stays finite."""
    from ..light.lights import POINT_RADIUS

    v = [c[i] - o[i] for i in range(3)]
    closest = lanes.dot3(v, d)
    gap = lanes.clamp_min(lanes.length3(*[v[i] - closest * d[i] for i in range(3)]), POINT_RADIUS)
    a, b = lanes.atan((start - closest) / gap), lanes.atan((end - closest) / gap)
    t = lanes.clamp(closest + gap * lanes.tan(a + u * (b - a)), start, end)
    along = t - closest
    return t, gap / (lanes.clamp_min(b - a, 1e-30) * (gap * gap + along * along))


def _collision(q, vol, x: list, face, wall, facts):
    """At a path's collision x (three lanes): its albedo (three lanes: its volume's, the surface's
    where it met the surface, `face`; None: no surface), the surface's normal there (None: no
    surface) and where it goes on from (off the surface, `lift`, `wall` the hit's distance; `facts`
    what the surface's `hit` knew of it)."""
    albedo = [_pick(vol, [m.albedo for m in q.vols])] * 3
    if face is None:
        return albedo, None, x
    normal = q.surface.normal(x, facts)
    albedo = [lanes.where(face, a, b) for a, b in zip(q.surface.albedo(normal, facts), albedo)]
    return albedo, normal, [lanes.where(face, a, b) for a, b in zip(q.surface.lift(x, normal, wall, facts), x)]


def _scatter(q, vol, d: list, face, normal: list | None, facts, key, count, on):
    """The direction a path scatters to from d (three lanes) and its weight (three lanes), from
    three draws where `on`: the phase function of its volume (`_phase_sample`), or where it met
    the surface (`face`; None: no surface) the surface's `bounce` about the `normal`
    (`lambert_bounce`: BRDF·cos/pdf is the albedo, already taken). -> (them, the counters)."""
    u = []
    for _ in range(3):
        u.append(uniform_lanes(key, count))
        count = count + lanes.to_int32(on)
    turned, weight = _phase_sample(q, vol, d, u)
    if face is None:
        return turned, [weight] * 3, count
    bounce, gain = q.surface.bounce(facts, normal, d, u)
    return [lanes.where(face, a, b) for a, b in zip(bounce, turned)], [lanes.where(face, g, weight) for g in gain], count


def _blended(q, vol, t, camera, later, beta: list, out: list):
    """The sky blend (`physical.sky_blend`) at collisions on the camera ray (`camera`) at distance
    t in a volume that has one: the march's source there is mix(S, σt·sky, w), so the collision's
    estimate S/σt becomes (1 − w)·S/σt + w·sky behind the ray (`q.behind`): the throughput of
    everything the path gathers from here on times 1 − w, and w·sky added where the paths give
    that light (`later`; on `single = "march"` the march gives it). -> (beta, out)."""
    if all(m.blend is None for m in q.vols):
        return beta, out
    w = lanes.where(camera, _pick(vol, [0.0 if m.blend is None else sky_blend_weight(m.blend, t) for m in q.vols]), 0.0)
    gain = camera & later
    out = [lanes.where(gain, out[c] + beta[c] * w * q.behind[c], out[c]) for c in range(3)]
    return [b * (1.0 - w) for b in beta], out


def _emitted(q, vol, x: list, sig) -> list:
    """σe/σ_t (three lanes) at a real collision at x in each lane's volume (σ_t `sig` there):
    `emission` · density plus the emission map, over σ_t."""
    out = [None] * 3
    for v, m in enumerate(q.vols):
        density = sig / lanes.clamp_min(m.sigma_t, 1e-30)
        source = [m.emission[c] * density for c in range(3)]
        if m.glow is not None:
            source = [a + b for a, b in zip(source, m.glow(x, density))]
        values = [c / lanes.clamp_min(sig, 1e-30) for c in source]
        out = values if v == 0 else [lanes.where(vol == v, values[c], out[c]) for c in range(3)]
    return out


def _roulette(beta: list, play, alive, key, count):
    """Russian roulette where `play`: a path goes on with probability q = min(1, ROULETTE_SCALE ×
    max |throughput|) (at least 0.05), its throughput over q. -> (throughput, alive, counters)."""
    q = lanes.clamp(lanes.maximum(lanes.maximum(lanes.abs(beta[0]), lanes.abs(beta[1])), lanes.abs(beta[2])) * ROULETTE_SCALE, 0.05, 1.0)
    u = uniform_lanes(key, count)
    count = count + lanes.to_int32(play)
    survive = ~play | (u < q)
    return [lanes.where(play & survive, b / q, b) for b in beta], alive & survive, count


def path_inputs(m: Media, lights: list, to, volume) -> SimpleNamespace:
    """What `trace_lanes` takes for paths of scenes `to.scene` [n]: `to` (as `fields.DENSITIES`'
    ``lanes`` inputs: per scene -> lanes `per_lane`, tables `floats`, `ints`) and `volume(v,
    state)` (its interval(o, d), its emission map's glow(x, density) or None: the backend's) ->
    the volumes' and lights' lanes. A scene of a surface alone gets a vacuum (`_vacuum`), so the
    tracking keeps its shape."""
    s, per_ray, vols = to.scene, to.per_lane, []
    for v, state in enumerate(m.vols):
        p = state.params
        kind, fn = p.phase.kind, state.phase.caps["lanes"]
        phase_q = fn[0](p.phase.value, SimpleNamespace(per_lane=per_ray))
        g = phase_q if kind in ("hg", "mie") else (phase_q if kind == "dual_hg" else 0.0)
        lobe = (g[0], g[1], g[2]) if kind == "dual_hg" else (g, g, 0.0)
        interval, glow = volume(v, state)
        sigma_t = per_ray(p.sigma_t)
        table = None if m.local is None else m.local[v]
        local = None if table is None else _local_lanes(macro_lanes(table, to), sigma_t)
        vols.append(SimpleNamespace(interval=interval, reach=min(state.plan.reach, 3e38), majorant=per_ray(m.majorants[v]),
                                    local=local,
                                    sigma_t=sigma_t, albedo=per_ray(p.albedo), emission=per_ray(p.emission),
                                    glow=glow, lobe=lobe, weighted=kind in ("mie", "rayleigh"),
                                    blend=per_ray(p.sky_blend) if state.plan.sky_blend else None,
                                    phase=lambda cos, fn=fn, q=phase_q: fn[1](q, cos, 1.0)))
    if not vols and m.air is None:
        vols.append(_vacuum(per_ray(torch.zeros(int(s.max()) + 1 if s.numel() else 1, device=s.device))))
    return SimpleNamespace(vols=vols, lights=[_light(li, per_ray) for li in lights], surface=None, channel=None, behind=None)


def _local_lanes(table, sigma_t):
    """σ_t's local majorant at points x and how far along directions d from them it holds (three
    lanes each), from the macro cells' `table` (`local_majorant.macro_lanes`), lanes."""
    def at(x, d):
        bound, reach = bound_at(table, x, d)
        return bound * sigma_t, reach

    return at


def _vacuum(zero) -> SimpleNamespace:
    """A medium no ray crosses (its interval empty, σ_t 0; `zero` lanes of 0), for paths in a
    scene of a surface alone (`with_air` gives it its σ_t)."""
    return SimpleNamespace(interval=lambda o, d: (zero, zero - 1.0), reach=3e38, majorant=zero, local=None, sigma_t=zero, albedo=zero,
                           emission=[zero] * 3, glow=None, lobe=(zero, zero, zero), weighted=False, blend=None,
                           phase=lambda cos: cos * 0.0 + 1.0 / (4.0 * math.pi), sigma=lambda x, mask: x[0] * 0.0)


def _light(light, per_ray) -> SimpleNamespace:
    """A light's toward(x) -> (direction, irradiance (three lanes each), distance) in lanes."""
    from ..light.lights import point_lanes

    radiant = per_ray(light.radiant)
    if light.directional:
        direction = per_ray(light.direction)
        return SimpleNamespace(toward=lambda x: (direction, radiant, math.inf), position=None)
    position = per_ray(light.params.position)
    return SimpleNamespace(toward=lambda x: point_lanes(position, radiant, x), position=position)


def radiance(m: Media, lights: list, rays, background: Tensor | None, sky, *, bounces: int, samples: int,
             keys: Tensor, trace=None) -> Tensor:
    """The path-traced radiance [n, 3] of camera `rays` [n]: the mean of `samples` paths a ray
    (`keys` [n, 3]: `geometry.sampling.ray_keys`), each of at most `bounces` scatterings, lit by
    `lights` (the render's `LightSource`s), seeing `background` [n, 3] (None: black) where the camera
    ray leaves the media (and its volumes' sky blend takes) and `sky(directions [m, 3], s [m]) ->
    [m, 3]` (None: black) where a scattered path does. `trace(m, lights, rays, key, bounces,
    channel, background)` runs paths (None: `trace_eager`; `path_kernel.trace_kernel`: Dr.Jit
    kernels), several samples' at once (`PATH_LANES` paths a call at most where a sample has fewer)."""
    s, n, total = rays.scene_index, len(rays), rays.origins.new_zeros(len(rays), 3)
    run, group = trace_eager if trace is None else trace, max(1, PATH_LANES // max(1, len(rays)))
    for start in range(0, samples, group):
        ks = range(start, min(samples, start + group))
        channel = None if m.air is None else torch.cat([hero_channels(keys, k) for k in ks])
        key = torch.cat([path_keys(keys, k, samples) for k in ks])
        behind = None if background is None else background.repeat(len(ks), 1)
        results = run(m, lights, rays.repeat(len(ks)), key, bounces, channel, behind)
        for j in range(len(ks)):  # each sample's in turn: the sum's order does not depend on the group
            out, beta, direction, gone, scattered, cut, above = (r[j * n:(j + 1) * n] for r in results)
            m.counts.truncated += int(cut.sum())
            m.counts.above_majorant += int(above.sum())
            first, later = (gone & (scattered == 0)).nonzero().squeeze(1), (gone & (scattered > 0)).nonzero().squeeze(1)
            if background is not None and first.numel() and not m.marched_first:
                out[first] = out[first] + beta[first] * background[first]
            if sky is not None and later.numel():
                out[later] = out[later] + beta[later] * sky(direction[later], s[later])
            total = total + out
    return total / samples


def trace_eager(m: Media, lights: list, rays, key: Tensor, bounces: int, channel: Tensor | None = None,
                behind: Tensor | None = None) -> list:
    """`trace_lanes` on torch columns for rays [n] (paths of keys `key` [n], colours `channel` [n]
    where the scene has air, `hero_channels`; the sky `behind` each ray [n, 3], None: black) -> its
    results as tensors ([n, 3] for the three-lane ones)."""
    s = rays.scene_index
    to = torch_inputs(s)
    per_ray = to.per_lane

    def volume(v, state):
        def interval(o, d):
            return state.intersect(torch.stack(o, dim=1), torch.stack(d, dim=1), s)

        glow = None
        if state.plan.emission_map is not None:
            fn = EMISSION_MAPS[state.plan.emission_map].fn
            glow = lambda x, density: lanes.columns(fn(state.params.emission_map.value, torch.stack(x, dim=1), density, s))  # noqa: E731
        return interval, glow

    def sigma(v, x, mask):
        out, rows = x[0].new_zeros(x[0].shape), mask.nonzero().squeeze(1)
        if rows.numel():
            state = m.vols[v]
            out[rows] = take(state.params.sigma_t, s[rows]) * state.field(torch.stack([c[rows] for c in x], dim=1), s[rows])
        return out

    q = path_inputs(m, lights, to, volume)
    q.sigma, q.behind = sigma, [0.0] * 3 if behind is None else lanes.columns(behind)
    if m.surface is not None:
        q.surface = m.surface(s, per_ray, rays.origins[:, 0], kernel=False)
    q = with_air(q, m, channel, per_ray)
    res = trace_lanes(q, list(rays.origins.unbind(1)), list(rays.directions.unbind(1)), key, bounces=bounces,
                      marched_first=m.marched_first)
    return [torch.stack(res[0:3], 1), torch.stack(res[3:6], 1), torch.stack(res[6:9], 1), res[9], res[10], res[11], res[12]]


__all__ = ["Media", "PathCounts", "air_media", "hero_channels", "hg_cos", "majorant", "media", "path_inputs", "path_keys", "radiance", "trace_eager", "trace_lanes",
           "track_lanes", "uniform_lanes"]
