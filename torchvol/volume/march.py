"""Sample placement and the march loop: over steps, vectorised over the rays still active.

Two step semantics share one loop:

- ``segments`` (physical): the interval [t0, t1] is cut into segments [t, t + dt] clipped so the
  last one ends exactly at t1; each is sampled at its midpoint. A dither ξ ∈ [0, 1) makes the first
  segment ξ·dt long, so [t0, t1] stays covered exactly.
- ``shader`` (the seeds' loop): sample at t, advance t += dt, stop once t > t1; the first sample is
  always taken, the start is t0 + dither.

Rays leave the batch when they finish (past t1, transmittance under `min_transmittance`, step
limit): every step evaluates only the rays still active, and their state is compacted with them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Literal

import torch
from torch import Tensor

from .integrate import alpha_linear_step, alpha_step, frostbite_step, riemann_step

Placement = Literal["count", "size", "adaptive"]
# medium(ray_ids [n], t [n], dt [n]) -> (sigma_t or alpha [n], source or colour [n, C])
Medium = Callable[[Tensor, Tensor, Tensor], tuple[Tensor, Tensor]]


@dataclass(frozen=True)
class StepRule:
    """How long the next step is.

    count: (t1 − t0)/steps per ray; size: step_size; adaptive: max(step_size, step_growth·t)
    (the seeds' `max(0.05, 0.02*t)`). `steps` is the count, or the step limit for the others."""

    placement: Placement
    steps: int
    step_size: float = 0.0
    step_growth: float = 0.0

    def length(self, t: Tensor, span: Tensor) -> Tensor:
        """`t`: [n] current distance; `span`: [n] t1 − t0 of the ray. -> [n]."""
        if self.placement == "count":
            return span / self.steps
        if self.placement == "size":
            return torch.full_like(t, self.step_size)
        return torch.clamp_min(self.step_growth * t, self.step_size)

    @property
    def max_iterations(self) -> int:
        # a dithered first segment adds one partial step to a fixed count
        return self.steps + 1 if self.placement == "count" else self.steps


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
    min_transmittance: float = 0.0,
) -> MarchResult:
    """March R rays through [t0, t1] where `hit`. `t0`, `t1`: [R]; `hit`: [R] bool; `dither`: [R]
    in [0, 1) (segments: fraction of the first step) or an absolute start offset (shader).

    `medium` returns (σ_t, source) for ``segments`` and (alpha, colour) for ``shader``, whose
    samples always composite as the seeds' alpha; `integrator` applies to ``segments``."""
    r = t0.shape[0]
    zeros = t0.new_zeros(r)
    out = MarchResult(
        radiance=t0.new_zeros(r, channels), transmittance=torch.ones_like(t0), weight_sum=zeros.clone(),
        weighted_t=zeros.clone(), median_t=zeros.clone(), steps=torch.zeros(r, dtype=torch.long, device=t0.device),
        truncated=torch.zeros(r, dtype=torch.bool, device=t0.device),
    )
    ids = hit.nonzero().squeeze(1)
    if ids.numel() == 0:
        return out
    # compacted state of the active rays
    t_start, t_end = t0[ids], t1[ids]
    span = t_end - t_start
    if semantics == "shader":
        t = t_start + (dither[ids] if dither is not None else 0.0)
        first = torch.zeros_like(t, dtype=torch.bool)
    else:
        t = t_start.clone()
        first = torch.ones_like(t, dtype=torch.bool) if dither is not None else torch.zeros_like(t, dtype=torch.bool)
        frac = dither[ids] if dither is not None else None
    trans = torch.ones_like(t)
    radiance = t.new_zeros(t.shape[0], channels)
    wsum, wt, median = torch.zeros_like(t), torch.zeros_like(t), torch.zeros_like(t)
    step_fn = {"riemann": riemann_step, "frostbite": frostbite_step, "alpha": alpha_linear_step}[integrator]

    def retire(keep: Tensor, truncated: Tensor | None = None) -> None:
        done = ~keep
        if done.any():
            d_ids = ids[done]
            out.radiance[d_ids] = radiance[done]
            out.transmittance[d_ids] = trans[done]
            out.weight_sum[d_ids] = wsum[done]
            out.weighted_t[d_ids] = wt[done]
            out.median_t[d_ids] = median[done]
            if truncated is not None:
                out.truncated[d_ids] = truncated[done]

    for step in range(rule.max_iterations):
        dt = rule.length(t, span)
        if semantics == "segments":
            if dither is not None:
                dt = torch.where(first, dt * frac, dt)
            dt = torch.minimum(dt, t_end - t)
            t_sample = t + 0.5 * dt
        else:
            t_sample = t
        value, color = medium(ids, t_sample, dt)
        if semantics == "shader":  # the medium gives opacities directly
            contrib, seg_trans = alpha_step(color, value)
        else:
            contrib, seg_trans = step_fn(color, value, dt)
        weight = trans * (1.0 - seg_trans)
        radiance = radiance + trans[:, None] * contrib
        wsum = wsum + weight
        wt = wt + weight * t_sample
        new_trans = trans * seg_trans
        crossed = (trans > 0.5) & (new_trans <= 0.5)
        if crossed.any():
            if semantics == "shader":
                t_cross = t_sample
            else:  # exponential inside the segment: T(s) = T·e^{−σ s}
                sigma = value.clamp_min(torch.finfo(t.dtype).tiny)
                t_cross = t + torch.minimum(torch.log(trans / 0.5) / sigma, dt)
            median = torch.where(crossed, t_cross, median)
        trans = new_trans
        t = t + dt
        if semantics == "segments":
            first = torch.zeros_like(first)
            inside = t < t_end
        else:
            inside = t <= t_end
        keep = inside & (trans >= min_transmittance) if min_transmittance > 0 else inside
        last = step == rule.max_iterations - 1
        retire(keep & ~torch.tensor(last), truncated=inside & (trans >= min_transmittance) if last else None)
        out.steps[ids] += 1
        if last:
            break
        keep_idx = keep.nonzero().squeeze(1)
        if keep_idx.numel() == 0:
            break
        if keep_idx.numel() < keep.numel():
            ids, t, t_end, span, trans, radiance = ids[keep_idx], t[keep_idx], t_end[keep_idx], span[keep_idx], trans[keep_idx], radiance[keep_idx]
            wsum, wt, median, first = wsum[keep_idx], wt[keep_idx], median[keep_idx], first[keep_idx]
            if semantics == "segments" and dither is not None:
                frac = frac[keep_idx]
    return out


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
