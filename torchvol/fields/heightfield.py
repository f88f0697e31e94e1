"""The terrain's heightfield written once in lanes (`ops.lanes`): its height, its sphere-tracing
step and refinement, the eager `terrain` module's rules, and their Dr.Jit loops (a primary ray's
trace, a shadow ray's visibility) for the kernels (`terrain.trace_kernel`, `volume.kernel_march`)."""

from __future__ import annotations

from types import SimpleNamespace

import torch

from ..geometry.rays import slab_interval
from ..noise import fast as fastnoise
from ..noise import lattice as noise
from ..ops import lanes
from ..schema.batch import Stacked
from .fbm import planar_basis


def terrain_lanes(t: Stacked, to, dtype: torch.dtype) -> SimpleNamespace:
    """What the terrain's height and its tracing take per lane (`to` as a density's lanes inputs:
    `per_lane`, `scene`, `ints`, `floats`, `number`; `dtype` the lanes' float type)."""
    q = SimpleNamespace(**{k: to.per_lane(getattr(t, k)) for k in ("base", "amplitude", "frequency", "safety", "epsilon",
                                                                 "max_distance")})
    q.octaves, q.steps = int(t.octaves), int(t.steps)
    q.scales = [to.number(c) for c in noise.folded_scales(q.octaves, dtype=dtype, device="cpu")]
    q.basis = planar_basis(t.seed, t.hash, to, dtype)  # the heights' noise lies on y = 0
    return q


def height_lanes(q: SimpleNamespace, x, z):
    """base + amplitude · fbm(frequency · (x, 0, z)) in lanes (`ops.lanes`): `noise.fbm`'s octaves
    of value noise in [−1, 1], in its float order; `q` from `terrain_lanes`."""
    u, w = q.frequency * x, q.frequency * z
    f = fastnoise.fbm_sum(lambda a, b, c: q.basis(a, b, c) * 2.0 - 1.0, u, lanes.full_like(u, 0.0), w, q.scales, None,
                          q.octaves, 0.5)
    return q.base + q.amplitude * f


def normal_lanes(q: SimpleNamespace, x, z) -> list:
    """The unit surface normal (three lanes) at horizontal lanes `x`, `z` on the terrain: central
    differences of the height, a hundredth of the finest octave's period apart; `q` from `terrain_lanes`."""
    e = (0.01 * noise.finest_period(q.octaves)) / q.frequency
    slope_x = -(height_lanes(q, x + e, z) - height_lanes(q, x - e, z)) / (2.0 * e)
    slope_z = -(height_lanes(q, x, z + e) - height_lanes(q, x, z - e)) / (2.0 * e)
    length = lanes.sqrt(slope_x * slope_x + 1.0 + slope_z * slope_z)  # ≥ 1: no division by 0
    return [slope_x / length, 1.0 / length, slope_z / length]


def trace_step(q: SimpleNamespace, o, d, t, last_t, last_g, first):
    """One sphere-tracing step of `trace` at distance `t` along rays `o`, `d` (three lanes each),
    lanes (`ops.lanes`): the gap there; the hit rule (under ε·(1 + t)); where a step crossed the
    surface, the secant root between the last point (`last_t`, its gap `last_g`; unread on the
    `first` step: True, False, or a lane) and this one; the next point, `safety` · gap on. `q`: safety, epsilon and
    height(x, z). -> (done, t (on the secant where it overshot), the next t, the gap)."""
    g = (o[1] + t * d[1]) - q.height(o[0] + t * d[0], o[2] + t * d[2])
    done = g < q.epsilon * (1.0 + t)
    if first is not True:  # a step that crossed the surface: the secant root between the two points
        over = done & (g < 0.0) if first is False else done & (g < 0.0) & ~first
        frac = last_g / lanes.clamp_min(last_g - g, lanes.tiny(g))
        t = lanes.where(over, last_t + frac * (t - last_t), t)
    return done, t, t + q.safety * g, g


def onto_surface(q: SimpleNamespace, o, d, t):
    """One secant step from `t` onto the surface, through the gap there and a hit-rule width back
    along the ray (lanes; `q`: epsilon and height(x, z)); a ray along which the gap does not fall
    stays. Never behind the ray's origin: a camera under the surface meets the ground at 0."""
    back = 2.0 * q.epsilon * (1.0 + t)
    gaps = []
    for at in (t, t - back):
        gaps.append((o[1] + at * d[1]) - q.height(o[0] + at * d[0], o[2] + at * d[2]))
    fall = gaps[1] - gaps[0]  # > 0 where the gap shrinks along the ray
    step = lanes.where(fall > 0, back * gaps[0] / lanes.clamp_min(fall, lanes.tiny(t)), lanes.full_like(t, 0.0))
    return lanes.clamp_min(t + lanes.minimum(lanes.maximum(step, -back), 2.0 * back), 0.0)


def trace_lanes(q: SimpleNamespace, o, d, t_max, *, refine: bool):
    """`trace` as a Dr.Jit loop per ray (its step `trace_step`, its refinement `onto_surface`):
    rays `o`, `d` (three lanes each) up to `t_max` (a lane or a number); `q` from
    `terrain_lanes`. -> (hit, t) lanes."""
    import drjit as dr
    from drjit.llvm import Int32

    pad = 1e-3 * (1.0 + q.amplitude)
    near, far = slab_interval(o, d, q.base - q.amplitude - pad, q.base + q.amplitude + pad)
    t0, t1 = lanes.clamp_min(near, 0.0), lanes.minimum(far, lanes.minimum(t_max, q.max_distance))
    live = t1 > t0
    rule = SimpleNamespace(safety=q.safety, epsilon=q.epsilon, height=lambda x, z: height_lanes(q, x, z))
    under = (o[1] < q.base + q.amplitude) & ((o[1] - rule.height(o[0], o[2])) < 0.0)  # the ground is solid
    dist = dr.select(under | ~live, 0.0, t0)

    def step(t, going, hit, i, last_t, last_g):
        done, ti, nxt, g = trace_step(rule, o, d, t, last_t, last_g, i == 0)
        keep = ~done & (nxt <= t1)
        return dr.select(keep, nxt, ti), keep, hit | done, i + 1, ti, g

    start = (dist, live & ~under, under, dr.zeros(Int32, dr.width(t0)), dist, dist)
    dist, _, hit, *_ = dr.while_loop(start, lambda t, going, hit, i, *_: going & (i < q.steps), step, mode="symbolic")
    if refine:
        dist = dr.select(hit, onto_surface(rule, o, d, dist), dist)
    return hit, dist


def visible_lanes(q: SimpleNamespace, p, direction, distance):
    """`visibility` in lanes, for a Dr.Jit kernel: 1 where the ray from `p` along `direction`
    (three lanes each) reaches `distance` (a lane; inf: a sun) without meeting the terrain, else 0."""
    import drjit as dr

    hit, _ = trace_lanes(q, p, direction, distance, refine=False)
    return dr.select(hit, dr.zeros(type(p[0]), dr.width(hit)), dr.full(type(p[0]), 1.0, dr.width(hit)))


__all__ = ["height_lanes", "normal_lanes", "onto_surface", "terrain_lanes", "trace_lanes", "trace_step", "visible_lanes"]
