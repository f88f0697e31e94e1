"""Sample placement and the march loop: over steps, vectorised over the rays still active.

Two step semantics share one loop:

- ``segments`` (physical): the interval [t0, t1] is cut into segments [t, t + dt] clipped so the
  last one ends exactly at t1; each is sampled at its midpoint. A dither ξ ∈ [0, 1) makes the first
  segment ξ·dt long, so [t0, t1] stays covered exactly.
- ``shader`` (the seeds' loop): sample at t, advance t += dt, stop once t > t1; the first sample is
  always taken, the start is t0 + dither.

Rays finish past t1, under `min_transmittance` or at the step limit. A finished ray stays in the
batch, taking zero-length steps (no contribution, transmittance × 1), until fewer than
`COMPACT_BELOW` of the batch is still going; then the batch is compacted to the active rays. The
state is one (K, n) tensor, so compaction is one gather, and the ray ids the medium sees stay the
same object between compactions (a medium may keep its per-ray gathers); docs/VOLUMES.md has
what this saves over one tensor per quantity compacted after every step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Literal

import torch
from torch import Tensor

from ..ops import lanes
from ..ops.mathops import pow_, take_rows
from .integrate import alpha_linear_step, alpha_step, frostbite_step, riemann_step

Placement = Literal["count", "size", "adaptive"]
# rows of the march state
_T, _T_END, _T_STOP, _SPAN, _TRANS, _WSUM, _WT, _MEDIAN, _STEPS, _RADIANCE = range(10)
# Finished rays leave the batch once fewer than this fraction of it is still going; until then
# they take zero-length steps. For a cheap medium (a trilinear grid) that is cheaper than
# compacting after every step (docs/VOLUMES.md).
COMPACT_BELOW = 0.75
# medium(ray_ids [n], t [n], dt [n]) -> (sigma_t or alpha [n], source or colour [n, C]); dt = 0 marks
# a sample whose source is not used (a finished row; the adaptive march's whole-step sample), so a
# medium may skip its lighting there
Medium = Callable[[Tensor, Tensor, Tensor], tuple[Tensor, Tensor]]


def gathered(gather: Callable[[Tensor], tuple]) -> Callable[[Tensor], tuple]:
    """`gather(ids)` memoised on the identity of `ids` [n]: the march hands the medium the same ids
    tensor until it compacts, so a medium's per-ray gathers (origin, direction, ...) are redone
    only then."""
    last: list = [None, None]

    def at(ids: Tensor) -> tuple:
        if last[0] is not ids:
            last[0], last[1] = ids, gather(ids)
        return last[1]

    return at


def lod_drop(t: Tensor, scale: float | None) -> Tensor | None:
    """Octaves a field drops at distance `t` [n] (`march.lod`, the template's LOD): floor(log2(1 +
    scale·t)), from the field's own octave count; None without LOD."""
    if scale is None:
        return None
    return torch.floor(torch.log2(1.0 + t * scale)).long()


@dataclass(frozen=True)
class StepRule:
    """How long the next step is.

    count: (t1 − t0)/steps per ray; size: step_size; adaptive: max(step_size, step_growth·t)
    (the seeds' `max(0.05, 0.02*t)`). `steps` is the count, or the step limit for the others."""

    placement: Placement
    steps: int
    step_size: float = 0.0
    step_growth: float = 0.0

    def length(self, t, span):
        """`t`: [n] current distance; `span`: [n] t1 − t0 of the ray. -> [n]. Lanes (`ops.lanes`)."""
        if self.placement == "count":
            return lanes.divide(span, self.steps)
        if self.placement == "size":
            return lanes.full_like(t, self.step_size)
        return lanes.clamp_min(self.step_growth * t, self.step_size)

    @property
    def max_iterations(self) -> int:
        """The step limit of the loop: `steps`, plus one for count placement (a dithered first
        segment adds one partial step to a fixed count)."""
        return self.steps + 1 if self.placement == "count" else self.steps


@dataclass(frozen=True)
class MarchSettings:
    """A render's march settings, every key decided (`scene.quality.march_settings`: the scene's
    `march` table, the rest from its quality level)."""

    rule: StepRule
    integrator: Literal["riemann", "frostbite", "alpha"]
    dither: Literal["none", "hash", "sin"]
    dither_scale: float
    max_distance: float | None  # None: boxes and spheres unbounded, slabs SLAB_REACH
    min_transmittance: float
    density_threshold: float
    lod_scale: float | None
    closed_form: bool
    depth_threshold: float
    dtype: torch.dtype
    tolerance: float | None


@dataclass
class MarchResult:
    """Per ray, for R rays: `radiance` [R, C]; `transmittance` [R]; `weight_sum` [R] = Σ wᵢ and
    `weighted_t` [R] = Σ wᵢ tᵢ (expected termination distance = weighted_t / weight_sum);
    `median_t` [R] where transmittance crossed 0.5 (0 if never); `steps` [R] steps taken;
    `truncated` [R] rays stopped by the step limit before their exit."""

    radiance: Tensor
    transmittance: Tensor
    weight_sum: Tensor
    weighted_t: Tensor
    median_t: Tensor
    steps: Tensor
    truncated: Tensor

    @classmethod
    def empty(cls, like: Tensor, channels: int):
        """Rays that met nothing: no radiance, full transmittance. `like`: [R], for size/dtype/device."""
        r, long = like.shape[0], dict(dtype=torch.long, device=like.device)
        return cls(radiance=like.new_zeros(r, channels), transmittance=torch.ones_like(like), weight_sum=torch.zeros_like(like),
                   weighted_t=torch.zeros_like(like), median_t=torch.zeros_like(like), steps=torch.zeros(r, **long),
                   truncated=torch.zeros(r, dtype=torch.bool, device=like.device))


def march(
    t0: Tensor,
    t1: Tensor,
    hit: Tensor,
    medium: Medium,
    *,
    rule: StepRule,
    integrator: Literal["riemann", "frostbite", "alpha"],
    channels: int = 3,
    semantics: Literal["segments", "shader"] = "segments",
    dither: Tensor | None = None,
    dither_unit: Literal["step", "absolute"] = "step",
    min_transmittance: float = 0.0,
    occupied: tuple[Tensor, Tensor] | None = None,
    compact_below: float = COMPACT_BELOW,
    transmittance: Tensor | None = None,
) -> MarchResult:
    """March R rays through [t0, t1] where `hit`. `t0`, `t1`: [R]; `hit`: [R] bool; `dither`: [R]
    in [0, 1): segments: the fraction of the first step; shader: the start offset, in steps
    (`dither_unit` "step", the seeds' t += STEP_SIZE·hash) or in world units ("absolute": the
    template's t += 0.1·fract(sin(...)), its scale already applied).

    `medium` returns (σ_t, source) for ``segments`` and (alpha, colour) for ``shader``, whose
    samples always composite as the seeds' alpha; `integrator` applies to ``segments``.

    `occupied` = (t_first, t_last) [R] (``segments`` with count or size placement): σ_t is known
    to be 0 outside that span, so the march starts at the last segment boundary before t_first and
    stops once past t_last. The boundaries stay where the full march puts them: same samples where
    the medium is, none where it is not.

    `compact_below`: the batch drops its finished rays once fewer than this fraction is still
    going (1.0: after every step that finishes one; right when a medium sample costs more than a
    gather, as fbm octaves do). `transmittance` [R]: the rays' transmittance at t0 (None: 1), for
    a stretch behind others (a joint march's pieces): the results are then the whole ray's."""
    ids = hit.nonzero().squeeze(1)
    if ids.numel() == 0:
        return MarchResult.empty(t0, channels)
    state, first, frac = _march_start(t0, t1, ids, rule=rule, semantics=semantics, dither=dither, dither_unit=dither_unit,
                                      occupied=occupied, channels=channels, transmittance=transmittance)
    final = t0.new_zeros(_RADIANCE + channels, t0.shape[0])
    final[_TRANS] = 1.0
    truncated = torch.zeros_like(hit)
    step_fn = {"riemann": riemann_step, "frostbite": frostbite_step, "alpha": alpha_linear_step}[integrator]
    active = None  # None: every row is active; else [n] 1.0 / 0.0 (a float mask: it scales), rows finished but not compacted away yet
    for step in range(rule.max_iterations):
        keep = _march_step(state, ids, medium, step, rule=rule, semantics=semantics, step_fn=step_fn,
                           first=first, frac=frac, active=active, min_transmittance=min_transmittance)
        if step == rule.max_iterations - 1:
            truncated[ids] = keep
            break
        kept = int(keep.sum())
        if kept == 0:
            break
        if kept < compact_below * keep.shape[0]:
            (state, ids), active = _compact(final, state, ids, keep), None
        else:
            active = keep.to(state.dtype)
    final.index_copy_(1, ids, state)
    return MarchResult(radiance=final[_RADIANCE:].T.contiguous(), transmittance=final[_TRANS], weight_sum=final[_WSUM],
                       weighted_t=final[_WT], median_t=final[_MEDIAN], steps=final[_STEPS].long(), truncated=truncated)


def _compact(final: Tensor, state: Tensor, ids: Tensor, keep: Tensor) -> tuple[Tensor, Tensor]:
    """Writes the rows of `state` (K, n) not in `keep` [n] bool to their rays' columns of `final`
    (K, R); -> (the kept rows' state (K, m), their ray ids [m])."""
    done = (~keep).nonzero().squeeze(1)
    final.index_copy_(1, take_rows(ids, done), state.index_select(1, done))
    keep_idx = keep.nonzero().squeeze(1)
    return state.index_select(1, keep_idx), take_rows(ids, keep_idx)


def _march_start(t0: Tensor, t1: Tensor, ids: Tensor, *, rule: StepRule, semantics: str, dither: Tensor | None,
                 dither_unit: str, occupied: tuple[Tensor, Tensor] | None, channels: int,
                 transmittance: Tensor | None = None):
    """`march`'s state for the rays `ids` [n] (their transmittance `transmittance` [R], None: 1):
    (state (K, n), one row per quantity; `first` [n] bool, the rays whose first segment is
    dithered, or None; `frac` [n], that segment's fraction, or None)."""
    t_start, t_end = t0[ids], t1[ids]
    span = t_end - t_start
    first = frac = None
    if semantics == "shader":
        t = t_start
        if dither is not None:
            t = t + dither[ids] * (rule.length(t_start, span) if dither_unit == "step" else 1.0)
    else:
        t = t_start
        if dither is not None:
            first, frac = torch.ones_like(t, dtype=torch.bool), dither[ids]
    t_stop = t_end
    if occupied is not None:
        if semantics != "segments" or rule.placement == "adaptive":
            raise ValueError("march(occupied=...) needs segments with count or size placement")
        t, t_stop, first = occupied_start(t_start, t_end, occupied[0][ids], occupied[1][ids], rule=rule, frac=frac)
    # the active rays' state, one row per quantity: compacting it is one gather
    state = t.new_zeros(_RADIANCE + channels, t.shape[0])
    state[_T], state[_T_END], state[_T_STOP], state[_SPAN] = t, t_end, t_stop, span
    state[_TRANS] = 1.0 if transmittance is None else transmittance[ids]
    return state, first, frac


def occupied_start(t_start: Tensor, t_end: Tensor, t_first: Tensor, t_last: Tensor, *, rule: StepRule,
                   frac: Tensor | None) -> tuple[Tensor, Tensor, Tensor | None]:
    """Where a ``segments`` march over [t_start, t_end] (each [n]; its first segment `frac` [n] of
    a step, None: whole) starts and stops when σ_t is 0 outside [t_first, t_last] (each [n]): the
    last segment boundary of the full march before t_first, and t_last. -> (t [n], t_stop [n],
    whether its first segment is still the dithered one [n] bool, or None without dither)."""
    # uniform steps: boundaries t0, b1 = t0 + frac·Δ, b1 + Δ, ...
    delta = rule.length(t_start, t_end - t_start).clamp_min(torch.finfo(t_start.dtype).tiny)
    b1 = t_start + (delta * frac if frac is not None else delta)
    j = torch.floor((t_first - b1) / delta)
    later = j >= 0  # t_first lies past b1: start at the boundary b1 + jΔ just before it
    t = torch.where(later, b1 + j.clamp_min(0) * delta, t_start)
    return t, torch.minimum(t_last, t_end), None if frac is None else ~later


def _march_step(state: Tensor, ids: Tensor, medium: Medium, step: int, *, rule: StepRule, semantics: str,
                step_fn: Callable, first: Tensor | None, frac: Tensor | None, active: Tensor | None,
                min_transmittance: float) -> Tensor:
    """One step of `march` for every row of `state` (K, n), in place. -> keep [n] bool: the rows still going."""
    t, t_end, t_stop, span, trans = state[_T], state[_T_END], state[_T_STOP], state[_SPAN], state[_TRANS]
    dt = rule.length(t, span)
    if semantics == "segments":
        if first is not None and step == 0:  # only a ray's first segment is dithered
            dt = torch.where(first, dt * frac, dt)
        dt = torch.minimum(dt, t_end - t)
        if active is not None:  # a finished row takes a zero-length segment: no contribution, T × 1
            dt = dt * active
        t_sample = t + 0.5 * dt
    else:
        t_sample = t
    value, color = medium(ids, t_sample, dt)
    if semantics == "shader":  # the medium gives opacities directly
        contrib, seg_trans = alpha_step(color, value)
        if active is not None:
            contrib, seg_trans = contrib * active[:, None], 1.0 - active * (1.0 - seg_trans)
    else:
        contrib, seg_trans = step_fn(color, value, dt)
    _composite(state, contrib, seg_trans, value, t_sample, dt, shader=semantics == "shader", active=active)
    t += dt
    inside = t < t_stop if semantics == "segments" else t <= t_end
    keep = inside & (trans >= min_transmittance) if min_transmittance > 0 else inside
    if active is not None:
        keep = keep & (active > 0)
    return keep


def _composite(state: Tensor, contrib: Tensor, seg_trans: Tensor, value: Tensor, t_sample: Tensor, dt: Tensor, *,
               shader: bool, active: Tensor | None) -> None:
    """Adds a step's samples to `state` (K, n), in place: radiance from `contrib` [n, C], the
    weights, the median crossing and the step count; the transmittance times `seg_trans` [n]."""
    t, trans = state[_T], state[_TRANS]
    weight = trans * (1.0 - seg_trans)
    state[_RADIANCE:] += trans * contrib.T
    state[_WSUM] += weight
    state[_WT] += weight * t_sample
    new_trans = trans * seg_trans
    crossed = (trans > 0.5) & (new_trans <= 0.5)
    if crossed.any():
        if shader:
            t_cross = t_sample
        else:
            t_cross = median_crossing(t, trans, value, dt)
        state[_MEDIAN] = torch.where(crossed, t_cross, state[_MEDIAN])
    state[_STEPS] += 1.0 if active is None else active
    trans.copy_(new_trans)


def median_crossing(t, trans, sigma_t, dt):
    """Where a segment [t, t + dt] of extinction `sigma_t`, entered at transmittance `trans` > 0.5,
    takes it to 0.5: T(s) = T·e^{−σ s} (lanes, `ops.lanes`)."""
    sigma = lanes.clamp_min(sigma_t, lanes.tiny(sigma_t))
    return t + lanes.minimum(lanes.log(trans / 0.5) / sigma, dt)


def expected_depth_fraction(x: Tensor) -> Tensor:
    """For a homogeneous segment of optical depth x: E[s | terminated in it] / length
    = 1/x − 1/(eˣ − 1), stable (series below 0.1, → 1/2 as x → 0, → 1/x for large x)."""
    small = x < 0.1
    safe = torch.where(small, torch.ones_like(x), x)
    exact = 1.0 / safe - 1.0 / torch.expm1(safe)
    x2 = x * x
    series = 0.5 - x / 12.0 + x * x2 / 720.0 - x2 * x2 * x / 30240.0
    return torch.where(small, series, exact)


LN2 = math.log(2.0)


def positive_part_integral(c: Tensor, b: Tensor, a: Tensor, lo: float, hi: float) -> Tensor:
    """∫ max(c + b·x + a·x², 0) dx over [lo, hi], exactly: the quadratic's real roots cut the
    interval into three pieces of constant sign. `c`, `b`, `a`: [n] -> [n]. Roots are taken in the
    cancellation-free form (q = −(b + sign(b)√D)/2: c/q and q/a), so a → 0 gives the linear root."""
    disc = b * b - 4.0 * a * c
    root = disc.clamp_min(0.0).sqrt()
    q = -0.5 * (b + torch.where(b >= 0, root, -root))
    roots = torch.stack([q / a, c / q]).nan_to_num(nan=lo, posinf=hi, neginf=lo).clamp(lo, hi)
    roots = torch.where(disc >= 0, roots, torch.full_like(roots, lo)).sort(dim=0).values
    cuts = torch.cat([torch.full_like(roots[:1], lo), roots, torch.full_like(roots[:1], hi)])  # [4, n]

    def antiderivative(x: Tensor) -> Tensor:
        return x * (c + x * (0.5 * b + x * (a / 3.0)))

    mid = 0.5 * (cuts[1:] + cuts[:-1])
    positive = c + mid * (b + mid * a) > 0
    pieces = antiderivative(cuts[1:]) - antiderivative(cuts[:-1])
    return torch.where(positive, pieces, torch.zeros_like(pieces)).sum(dim=0)


def missed_depth(sigma_a: Tensor, sigma_m: Tensor, sigma_b: Tensor, dt: Tensor) -> Tensor:
    """Optical depth a step's samples do not see: the quadratic through the signed σ_t at
    t + dt/4, t + dt/2, t + 3dt/4 (`sigma_a`, `sigma_m`, `sigma_b` [n]; negative where there is no
    density) integrated where positive over the step [t, t + dt] (`dt` [n]), less what the two
    halves' midpoint samples already give. Where all three samples read 0 but the field rises
    towards 0 between them, an island of density may lie there: this is its estimated depth. -> [n] ≥ 0."""
    # in x = (t − midpoint)/(dt/4) the samples sit at −1, 0, 1 and the step spans [−2, 2]
    c, b, a = sigma_m, 0.5 * (sigma_b - sigma_a), 0.5 * (sigma_a + sigma_b) - sigma_m
    seen = 0.5 * (sigma_a.clamp_min(0.0) + sigma_b.clamp_min(0.0)) * dt
    return (positive_part_integral(c, b, a, -2.0, 2.0) * (0.25 * dt) - seen).clamp_min(0.0)


@dataclass
class AdaptiveResult(MarchResult):
    """`MarchResult` plus `error` [R]: the estimated absolute error of each ray's transmittance
    and radiance (in units of `radiance_scale`), and `evaluations` [R]: medium samples taken."""

    error: Tensor = None
    evaluations: Tensor = None

    @classmethod
    def empty(cls, like: Tensor, channels: int):
        """Rays that met nothing, with no error and no evaluations. `like`: [R], for size/dtype/device."""
        out = super().empty(like, channels)
        out.error, out.evaluations = torch.zeros_like(like), torch.zeros_like(out.steps)
        return out


def march_adaptive(
    t0: Tensor,
    t1: Tensor,
    hit: Tensor,
    medium: Medium,
    *,
    tolerance: float,
    integrator: Literal["riemann", "frostbite"] = "frostbite",
    radiance_scale: Tensor | float = 1.0,
    first_step: float | None = None,
    max_steps_per_span: int | None = None,
    max_step: Tensor | None = None,
    min_step: float = 1e-6,
    max_iterations: int = 4096,
    min_transmittance: float = 0.0,
    channels: int = 3,
    transmittance: Tensor | None = None,
) -> AdaptiveResult:
    """Error-controlled march: each step is taken once whole and once as two halves (step
    doubling); a third of their difference estimates the error of the halves, which are kept.
    The whole step samples σ_t alone: its source is its σ_t times the halves' source per unit σ_t
    (in-scattered light is σ_t times a light that varies slowly: the shadow's transmittance), so
    a step traces two shadow rays, not three (docs/QUALITY.md has what that saves).
    A step is accepted when that error, times the transmittance in front of it, is within
    `tolerance`·dt/(t1 − t0) — so the errors of a whole ray add up to at most about `tolerance`.
    The next step grows or shrinks by (allowed/error)^(1/3) (the local error of a midpoint step is
    third order in dt). Errors are absolute on transmittance and on radiance divided by
    `radiance_scale` ([R] or scalar: e.g. the lights' radiance).

    Step doubling is blind to density that lies between its samples: where all of them read 0 it
    estimates no error at all, and an island of clamped noise between them is stepped over. So
    the medium returns the *signed* σ_t (the field before its clamp at 0: negative by how far a
    point is from having density) and the error also counts `missed_depth`, the depth of the
    quadratic through the three signed samples where it rises above 0 unseen. Without it the
    error on an fbm cloud stopped at ~2.6e-4 however tight the tolerance (docs/QUALITY.md).

    `max_step` [R] caps steps in length (half the medium's `feature_size`: a whole feature narrower
    than a step falls between samples, where not even the quadratic sees it). `max_steps_per_span`:
    steps are never longer than (t1 − t0)/max_steps_per_span (for media with no feature size).

    `t0`, `t1`, `hit`: [R]; `medium(ids, t, dt) -> (signed σ_t [n], source [n, C])`, σ_t integrated
    clamped at 0; `transmittance` [R] or None: as `march`'s (its errors weighed by the whole ray's)."""
    step_fn = {"riemann": riemann_step, "frostbite": frostbite_step}[integrator]
    out, ids = AdaptiveResult.empty(t0, channels), hit.nonzero().squeeze(1)
    if ids.numel() == 0:
        return out
    rays = _AdaptiveRays.start(t0, t1, ids, radiance_scale=radiance_scale, first_step=first_step, channels=channels,
                               max_steps_per_span=max_steps_per_span, max_step=max_step, transmittance=transmittance)
    for _ in range(max_iterations):
        keep = _adaptive_step(rays, medium, step_fn, tolerance=tolerance, min_step=min_step,
                              min_transmittance=min_transmittance)
        if bool(keep.all()):  # nothing finished: the batch, and the ids the medium has gathered for, stay
            continue
        rays.write(out, ~keep)
        if not keep.any():
            return out
        rays.keep(keep.nonzero().squeeze(1))
    rays.write(out)
    out.truncated[rays.ids] = True
    return out


@dataclass
class _AdaptiveRays:
    """`march_adaptive`'s active rays, each field [n] (`radiance`, `light_prev` [n, C]; `samples`
    [3n], the ray of each sample: whole step, first half, second half). The fields named in
    `RESULTS` are the `AdaptiveResult` fields as they stand."""

    RESULTS = ("radiance", "transmittance", "weight_sum", "weighted_t", "median_t", "error", "steps", "evaluations")
    ids: Tensor
    samples: Tensor
    t: Tensor
    t_end: Tensor
    span: Tensor
    max_dt: Tensor
    dt: Tensor
    scale: Tensor
    light_prev: Tensor  # the light per unit σ_t at the last accepted step's second half,
    at_prev: Tensor  # and where (NaN: none yet)
    radiance: Tensor
    transmittance: Tensor
    weight_sum: Tensor
    weighted_t: Tensor
    median_t: Tensor
    error: Tensor
    steps: Tensor
    evaluations: Tensor

    @classmethod
    def start(cls, t0: Tensor, t1: Tensor, ids: Tensor, *, radiance_scale: Tensor | float, first_step: float | None,
              max_steps_per_span: int | None, max_step: Tensor | None, channels: int,
              transmittance: Tensor | None = None) -> _AdaptiveRays:
        """The rays `ids` [n] of `t0`, `t1` [R] at their entry (at `transmittance` [R], None: 1),
        nothing marched yet."""
        r = t0.shape[0]
        scale = torch.as_tensor(radiance_scale, dtype=t0.dtype, device=t0.device).expand(r)[ids].clamp_min(1e-30)
        t, t_end = t0[ids].clone(), t1[ids]
        span = (t_end - t).clamp_min(1e-30)
        max_dt = span / max_steps_per_span if max_steps_per_span is not None else span
        if max_step is not None:
            max_dt = torch.minimum(max_dt, max_step[ids])
        dt = span / 8 if first_step is None else torch.full_like(t, first_step)
        trans = torch.ones_like(t) if transmittance is None else transmittance[ids].clone()
        radiance = t.new_zeros(t.shape[0], channels)
        wsum, wt, median, err = (torch.zeros_like(t) for _ in range(4))
        return cls(ids=ids, samples=ids.repeat(3), t=t, t_end=t_end, span=span, max_dt=max_dt, dt=dt, scale=scale,
                   light_prev=t.new_zeros(t.shape[0], channels), at_prev=torch.full_like(t, math.nan),
                   radiance=radiance, transmittance=trans, weight_sum=wsum, weighted_t=wt, median_t=median, error=err,
                   steps=torch.zeros_like(ids), evaluations=torch.zeros_like(ids))

    def write(self, out: AdaptiveResult, rows: Tensor | None = None) -> None:
        """Writes the results of the rays at `rows` [n] bool (None: all) to their rays in `out`."""
        for name in self.RESULTS:
            if rows is None:
                getattr(out, name)[self.ids] = getattr(self, name)
            else:
                getattr(out, name)[self.ids[rows]] = getattr(self, name)[rows]

    def keep(self, k: Tensor) -> None:
        """Keeps the rays at rows `k` [m] only."""
        for name in ("ids", "t", "t_end", "span", "dt", "scale", "max_dt", "light_prev", "at_prev", *self.RESULTS):
            setattr(self, name, getattr(self, name)[k])
        self.samples = self.ids.repeat(3)


def _adaptive_step(rays: _AdaptiveRays, medium: Medium, step_fn: Callable, *, tolerance: float, min_step: float,
                   min_transmittance: float) -> Tensor:
    """One step-doubled step of every ray in `rays`, in place: accepted rays advance, every ray's
    next step length is chosen. -> keep [n] bool: the rays still going."""
    a = rays
    dt = torch.minimum(torch.minimum(torch.maximum(a.dt, torch.full_like(a.dt, min_step)), a.max_dt), a.t_end - a.t)
    n = a.t.shape[0]
    quarter = 0.25 * dt
    where = torch.cat([a.t + 2 * quarter, a.t + quarter, a.t + 3 * quarter])
    signed, halves_sigma, light, lit, contrib, seg = _doubled_samples(medium, step_fn, a.samples, where, dt, quarter, n)
    c_full, c_a, c_b = contrib[:n], contrib[n:2 * n], contrib[2 * n:]
    s_full, s_a, s_b = seg[:n], seg[n:2 * n], seg[2 * n:]
    c_half, s_half = c_a + s_a[:, None] * c_b, s_a * s_b
    # the halves' error is about a third of their difference from the whole step (2nd order);
    # that difference no longer sees the light's curvature, which the halves' error has:
    # σ_t·dt³·|L''|/96, L'' from the second divided difference of the light at the last
    # accepted step's second half and this step's halves
    previous = (light[0] - a.light_prev) / (where[n:2 * n] - a.at_prev)[:, None]
    curvature = 2.0 * ((light[1] - light[0]) / (2 * quarter)[:, None] - previous) / (where[2 * n:] - a.at_prev)[:, None]
    # (only where the three abscissae are apart: in float32 a step near min_step far along a ray
    # rounds them together, and 0/0 made the error, and with it the next step, NaN)
    apart = (where[2 * n:] > where[n:2 * n]) & (where[n:2 * n] > a.at_prev)
    curvature = torch.where((lit.all(0) & a.at_prev.isfinite() & apart)[:, None], curvature, 0.0)
    light_error = halves_sigma.mean(0) * dt**3 * curvature.abs().amax(dim=1) / (96.0 * a.scale)
    trans = a.transmittance
    local = trans * torch.maximum((s_full - s_half).abs() / 3.0, (c_full - c_half).abs().amax(dim=1) / (3.0 * a.scale) + light_error)
    local = torch.maximum(local, trans * missed_depth(signed[n:2 * n], signed[:n], signed[2 * n:], dt))
    allowed = tolerance * dt / a.span
    accept = (local <= allowed) | (dt <= min_step * 1.0001)
    a.evaluations += 3
    _accept_halves(a, accept, dt, c_half, s_half, local)
    a.light_prev = torch.where(accept[:, None], light[1], a.light_prev)
    a.at_prev = torch.where(accept, torch.where(lit[1], where[2 * n:], math.nan), a.at_prev)
    a.steps += accept.long()
    factor = (0.9 * pow_(allowed / local.clamp_min(1e-300), 1.0 / 3.0)).clamp(0.2, 4.0)
    a.dt = dt * factor
    return (a.t < a.t_end) & (a.transmittance >= min_transmittance)


def _doubled_samples(medium: Medium, step_fn: Callable, samples: Tensor, where: Tensor, dt: Tensor, quarter: Tensor,
                     n: int):
    """The n steps [t, t + dt] sampled whole and as two halves at `where` [3n] (rays `samples`
    [3n]). -> (signed σ_t [3n]; the halves' σ_t [2, n], their light per unit σ_t [2, n, C] and
    where it is lit [2, n] bool; the contributions [3n, C] and transmittances [3n] of the three
    segments)."""
    lengths = torch.cat([dt, 2 * quarter, 2 * quarter])
    # the whole step's sample asks for σ_t alone (dt = 0): its source is its σ_t times the
    # halves' light per unit σ_t, averaged (in-scattered light is σ_t times a slowly varying light)
    signed, source = medium(samples, where, torch.cat([torch.zeros_like(dt), lengths[n:]]))
    sigma = signed.clamp_min(0.0)
    halves_sigma = sigma[n:].view(2, n)
    lit = halves_sigma > 0
    light = torch.where(lit[..., None], source[n:].view(2, n, -1) / halves_sigma.clamp_min(1e-30)[..., None], 0.0)
    source = torch.cat([sigma[:n, None] * light.sum(0) / lit.sum(0).clamp_min(1)[:, None], source[n:]])
    contrib, seg = step_fn(source, sigma, lengths)
    return signed, halves_sigma, light, lit, contrib, seg


def _accept_halves(a: _AdaptiveRays, accept: Tensor, dt: Tensor, c_half: Tensor, s_half: Tensor, local: Tensor) -> None:
    """The rays where `accept` [n] advance by `dt` [n] with the two halves' result (`c_half`
    [n, C], `s_half` [n]) and add their error `local` [n]; in place."""
    trans = a.transmittance
    weight = torch.where(accept, trans * (1.0 - s_half), torch.zeros_like(a.t))
    t_mid = a.t + 0.5 * dt
    new_trans = torch.where(accept, trans * s_half, trans)
    crossed = accept & (trans > 0.5) & (new_trans <= 0.5)
    a.median_t = torch.where(crossed, t_mid, a.median_t)
    a.radiance = a.radiance + torch.where(accept[:, None], trans[:, None] * c_half, torch.zeros_like(c_half))
    a.weight_sum, a.weighted_t = a.weight_sum + weight, a.weighted_t + weight * t_mid
    a.error = a.error + torch.where(accept, local, torch.zeros_like(local))
    a.transmittance = new_trans
    a.t = torch.where(accept, a.t + dt, a.t)
