"""One march through every medium of a ray: the physically shaded volumes of a scene are marched
together, not one by one and composited whole (exact only where they do not overlap).

A ray's span is cut at every medium's entry and exit (its bounds, or with empty-space skipping its
occupied span); in each piece the media present are summed: σ_t = Σ σ_t,i and source =
Σ (σ_s,i p_i E T_light,i + σ_e,i), each medium's in-scatter with its own phase and shadow rays. A
piece where every medium present has a closed form (homogeneous, lit by unshadowed suns) is one
exact segment; the others are marched (`march.steps` per piece, or the error-controlled march).
The pieces do not overlap, so their front-to-back composite is exact, and the image does not
depend on the order of `[[volumes]]`. Where media do not overlap, each piece is one medium's
chord, marched as that medium alone would be.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from ..geometry.camera import Rays
from ..light.atmosphere import AirPath
from ..schema.batch import take
from . import kernel_march
from .composite import VolumePart
from .context import VolumeContext
from .march import MarchResult, Medium, StepRule, gathered, march, march_adaptive
from .physical import exact_segment
from .strategy import entry_exit, skipped_span


@dataclass(frozen=True)
class Joint:
    """The media's part of a chunk's rays [n] (`part`: radiance [n, 3], transmittance, weight
    sums, median t and first entry t0), and where asked each medium's share of its alpha
    (`shares` [V, n], Σ = 1 − transmittance; None: not asked)."""

    part: VolumePart
    shares: Tensor | None


def spans(ctx: VolumeContext, vols: Sequence, rays: Rays, t_limit: Tensor | None,
          air: AirPath | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """(t0, t1, hit) [V, n]: where each of the volumes `vols` holds medium along the chunk's rays:
    its bounds up to `t_limit` [n] (a surface), or its occupied span where it skips empty space;
    with `air`, row V is the air's span, up to `t_limit` too."""
    out = []
    if air is not None:
        t1 = air.leave if t_limit is None else torch.minimum(air.leave, t_limit)
        out.append((air.enter, t1, t1 > air.enter))
    for vol in vols:
        t0, t1, hit = entry_exit(vol, rays, t_limit)
        if vol.plan.strategy == "skip":
            with ctx.timer.section(vol.plan.skip_pass):
                (t0, t1), hit = skipped_span(vol, rays, t0, t1, hit)
        out.insert(len(out) - (air is not None), (t0, t1, hit))
    return tuple(torch.stack(x) for x in zip(*out))


def pieces(t0: Tensor, t1: Tensor, hit: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """A ray's span cut at every entry and exit of its media (`t0`, `t1`, `hit` [V, n]) -> (start,
    end [P, n], active [P, V, n]: medium v fills piece p of the ray), P = 2V − 1, in order along
    the ray; a piece of no length, or past the last exit, has no medium active."""
    far = torch.full_like(t0, math.inf)
    cuts = sorted_rows(torch.cat([torch.where(hit, t0, far), torch.where(hit, t1, far)]))  # [2V, n]
    start, end = cuts[:-1], cuts[1:]
    present = torch.isfinite(end) & (end > start)
    active = hit[None] & (t0[None] <= start[:, None]) & (t1[None] >= end[:, None]) & present[:, None]
    return start, end, active


def sorted_rows(x: Tensor) -> Tensor:
    """x [m, n] sorted along dim 0: for a ray's few cuts (m ≤ 8) an odd-even transposition network
    of torch.minimum / maximum (m rounds), the values `x.sort(dim=0)` gives at a tenth to a
    twentieth of its time (torch sorts a strided dim column by column: 1.8 ms for 2 × 65 k)."""
    m = x.shape[0]
    if m > 8:
        return x.sort(dim=0).values
    rows = list(x.unbind(0))
    for r in range(m):
        for i in range(r % 2, m - 1, 2):
            rows[i], rows[i + 1] = torch.minimum(rows[i], rows[i + 1]), torch.maximum(rows[i], rows[i + 1])
    return torch.stack(rows)


def summed_medium(media: Sequence[Medium], active: Tensor, *, shares: bool, signed: bool,
                  air: AirPath | None = None) -> Medium:
    """The media of one piece as one: at each sample the σ_t and sources of the media `active`
    [V, R] on its ray summed (with `air`, row V of `active` is the air's: its in-scatter is added
    where it is active, and every source reaches the camera through the air in front of it, an RGB
    transmittance). `shares`: the source has V channels more, σ_t,v each (integrated like a
    source, they give each medium's share of the alpha). `signed`: the media return signed σ_t
    (`march_adaptive`); the sum is the positive parts' where any is positive, else the largest."""
    # per medium, the rows of a sample batch on its rays: memoised on the march's ids, so a
    # medium's own gathers (`gathered`) see the same sub-ids object until the march compacts
    subsets = [gathered(lambda ids, a=a: _rows(a[ids], ids)) for a in active]
    volumes = medium_sum(media, subsets, shares=shares, signed=signed)
    if air is None:
        return volumes

    def through_air(ids: Tensor, t: Tensor, dt: Tensor) -> tuple[Tensor, Tensor]:
        sigma, source = volumes(ids, t, dt)
        rows, sub = subsets[-1](ids)
        if sub is not None:  # the air's own in-scatter (σ_t 0: its extinction is the RGB factor below)
            if rows is None:
                source[:, :3] += air.source(sub, t)
            else:
                source[rows, :3] += air.source(sub, t[rows])
        source[:, :3] *= air.transmittance(ids, t)
        return sigma, source

    return through_air


def medium_sum(media: Sequence[Medium], subsets: Sequence, *, shares: bool, signed: bool) -> Medium:
    """`summed_medium` of the volumes' `media` alone, each on the rows `subsets[v](ids)` gives."""

    def medium(ids: Tensor, t: Tensor, dt: Tensor) -> tuple[Tensor, Tensor]:
        n = ids.shape[0]
        sigma = t.new_zeros(n)
        largest = torch.full_like(sigma, -math.inf) if signed else None  # (only the signed sum reads it)
        source = t.new_zeros(n, 3 + (len(media) if shares else 0))
        for v, med in enumerate(media):
            rows, sub = subsets[v](ids)
            if sub is None:
                continue
            sig, src = med(sub, t, dt) if rows is None else med(sub, t[rows], dt[rows])
            positive = sig.clamp_min(0.0)
            if signed:
                largest = torch.maximum(largest, sig) if rows is None else largest.scatter_reduce(0, rows, sig, "amax")
            if rows is None:
                sigma = sigma + positive
                source[:, :3] += src
                if shares:
                    source[:, 3 + v] = positive
            else:
                sigma.index_add_(0, rows, positive)
                source[rows, :3] += src
                if shares:
                    source[rows, 3 + v] = positive
        if signed:  # (a sample with no volume on it, the air's alone, has σ_t 0)
            sigma = torch.where(sigma > 0, sigma, torch.where(torch.isfinite(largest), largest, 0.0))
        return sigma, source

    return medium


def _rows(on: Tensor, ids: Tensor) -> tuple[Tensor | None, Tensor | None]:
    """Of a sample batch's rays `ids` [n], those where a medium is present (`on` [n] bool) ->
    (their rows [m] or None: all, their ids [m] or None: none)."""
    if bool(on.all()):
        return None, ids
    rows = on.nonzero().squeeze(1)
    return (rows, ids[rows]) if rows.numel() else (None, None)


def march_piece(ctx: VolumeContext, medium: Medium, rays: Rays, start: Tensor, end: Tensor, rows: Tensor,
                exact: Tensor, front: Tensor, *, channels: int, dither: Tensor | None, features: Tensor | None,
                compact_below: float, air_only: Tensor | None = None, air_steps: int = 0) -> VolumePart:
    """One piece [start, end] [n] of the rays `rows` [n] bool through `medium`, behind the
    transmittance `front` [n]: one exact segment where `exact` [n] bool (every medium there has a
    closed form), `air_steps` equal steps where `air_only` [n] bool (only the air is there: smooth,
    it takes the atmosphere's own step count), else the march the settings ask for (`dither` [n]
    or None: the march's start offsets; `features` [n]: the finest feature size of the media
    there, inf where none, or None). -> the piece's share of the whole ray's radiance, weight sums
    and median crossing (0: none in it), and the ray's transmittance behind it (`front` off `rows`)."""
    st, marched = ctx.settings, rows & ~exact
    if air_only is not None:
        marched = marched & ~air_only
    if st.tolerance is not None:
        res = march_adaptive(
            start, end, marched, medium, tolerance=st.tolerance, integrator=st.integrator, channels=channels,
            radiance_scale=ctx.radiance_scale(rays.scene_index), min_transmittance=st.min_transmittance,
            max_steps_per_span=st.rule.steps if st.rule.placement == "count" and features is None else None,
            max_step=None if features is None else 0.5 * features, transmittance=front)
        ctx.counts.error_estimate = max(ctx.counts.error_estimate, float(res.error.max()) if len(res.error) else 0.0)
    else:
        res = fixed_march(ctx, medium, start, end, marched, st.rule, channels=channels, dither=dither,
                          compact_below=compact_below, front=front)
    out = dict(radiance=res.radiance, transmittance=res.transmittance, weight_sum=res.weight_sum,
               weighted_t=res.weighted_t, median_t=res.median_t)
    if air_only is not None and bool(air_only.any()):
        res = fixed_march(ctx, medium, start, end, air_only, StepRule("count", air_steps), channels=channels,
                          dither=dither, compact_below=compact_below, front=front)
        for key, value in out.items():
            out[key] = torch.where(air_only.view(-1, *([1] * (value.dim() - 1))), getattr(res, key), value)
    ids = exact.nonzero().squeeze(1)
    if ids.numel():
        a, length = start[ids], end[ids] - start[ids]
        sigma, source = medium(ids, a + 0.5 * length, length)
        for key, value in exact_segment(source, sigma.clamp_min(0.0), a, length, front[ids]).items():
            out[key][ids] = value
    out["transmittance"] = torch.where(rows, out["transmittance"], front)
    return VolumePart(**out, t0=torch.where(rows, start, torch.full_like(start, math.inf)))


def fixed_march(ctx: VolumeContext, medium: Medium, start: Tensor, end: Tensor, rows: Tensor, rule: StepRule, *,
                channels: int, dither: Tensor | None, compact_below: float, front: Tensor) -> MarchResult:
    """`march` of the rays `rows` [n] bool over [start, end] [n] behind the transmittance `front`
    [n] by `rule`, with the render's integrator, dither and early termination; its steps counted
    in the render's stats."""
    st = ctx.settings
    res = march(start, end, rows, medium, rule=rule, integrator=st.integrator, channels=channels, dither=dither,
                dither_unit="absolute" if st.dither == "sin" else "step", min_transmittance=st.min_transmittance,
                compact_below=compact_below, transmittance=front)
    ctx.counts.march_steps += int(res.steps.sum())
    ctx.counts.truncated_rays += int(res.truncated.sum())
    return res


def march_joint(ctx: VolumeContext, vols: Sequence, rays: Rays, background: Tensor | None, t_limit: Tensor | None,
                *, shares: bool = False, air: AirPath | None = None) -> Joint:
    """The volumes `vols` (physically shaded) marched together along a chunk's `rays` [n] (the sky
    behind them `background` [n, 3] or None, surfaces at `t_limit` [n] or None), with `air` (the
    `[atmosphere]` along the rays) a medium of the march where given. `shares`: also each medium's
    share of the alpha (the labels). -> `Joint`."""
    t0, t1, hit = spans(ctx, vols, rays, t_limit, air)
    start, end, active = pieces(t0, t1, hit)
    first = torch.where(hit, t0, torch.full_like(t0, math.inf)).amin(dim=0)  # (the air's entry too)
    if ctx.plan.joint is not None and ctx.plan.joint.backend == "drjit":  # one Dr.Jit kernel
        res = kernel_march.march(ctx, vols, rays, background, start, end, active, ctx.dither(rays), shares=shares,
                                 air=air)
        if bool(active.any()):  # the members' per-sample passes ran inside it, their time in its own
            for name in (n for vol in vols for n in vol.plan.sample_passes):
                with ctx.timer.section(name):
                    pass
        part = VolumePart(radiance=res.radiance[:, :3], transmittance=res.transmittance, weight_sum=res.weight_sum,
                          weighted_t=res.weighted_t, median_t=res.median_t, t0=first)
        return Joint(part, _alpha_shares(res.radiance[:, 3:].T, res.transmittance) if shares else None)
    signed = ctx.settings.tolerance is not None
    media = [vol.shading.fn(ctx, vol, rays, background, signed=signed) for vol in vols]
    # the air varies along every ray: a piece with air is marched
    closed = torch.tensor([vol.plan.strategy == "closed_form" for vol in vols] + [False] * (air is not None),
                          dtype=torch.bool, device=t0.device)
    feature = [vol.field.feature_size for vol in vols] + [None] * (air is not None)
    compact_below = max([vol.plan.compact_below for vol in vols], default=1.0)
    channels = 3 + (len(vols) if shares else 0)
    front, floor = torch.ones_like(start[0]), ctx.settings.min_transmittance
    # each piece adds its share of the whole ray's radiance (and σ_t shares) and weights
    radiance, wsum, wt, median = start.new_zeros(start.shape[1], channels), *(torch.zeros_like(front) for _ in range(3))
    dither = ctx.dither(rays)
    air_steps = 0 if air is None else air.nodes
    for p in range(start.shape[0]):
        rows = active[p].any(dim=0) & (front >= floor) if floor > 0 else active[p].any(dim=0)
        if not bool(rows.any()):
            continue
        exact = rows & ~(active[p] & ~closed[:, None]).any(dim=0)
        features = None
        if any(f is not None for f in feature) and ctx.settings.tolerance is not None:
            features = torch.stack([torch.where(active[p, v], take(f, rays.scene_index), math.inf)
                                    for v, f in enumerate(feature) if f is not None]).amin(dim=0)
        medium = summed_medium(media, active[p], shares=shares, signed=signed, air=air)
        air_only = None if air is None else rows & ~active[p, :-1].any(dim=0)
        part = march_piece(ctx, medium, rays, start[p], end[p], rows, exact, front, channels=channels, dither=dither,
                           features=features, compact_below=compact_below, air_only=air_only, air_steps=air_steps)
        radiance, wsum, wt = radiance + part.radiance, wsum + part.weight_sum, wt + part.weighted_t
        median, front = torch.where(median == 0, part.median_t, median), part.transmittance
    part = VolumePart(radiance=radiance[:, :3], transmittance=front, weight_sum=wsum, weighted_t=wt, median_t=median,
                      t0=first)
    return Joint(part, _alpha_shares(radiance[:, 3:].T, front) if shares else None)


def _alpha_shares(raw: Tensor, trans: Tensor) -> Tensor:
    """Each medium's integrated σ_t share `raw` [V, n] scaled to sum to the alpha 1 − `trans` [n]
    (they do exactly for exact segments; a march's first-order sum is rescaled). -> [V, n]."""
    total = raw.sum(dim=0)
    scale = torch.where(total > 0, (1.0 - trans) / total.clamp_min(torch.finfo(trans.dtype).tiny), torch.zeros_like(total))
    return raw * scale
