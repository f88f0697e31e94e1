"""How one volume's rays are integrated, as the plan decided (`VolumePass.strategy`): in closed
form, by a fixed march, by a fixed march over the occupied span only (empty space skipped), or by
the error-controlled march. Each takes the render's state `ctx`, the volume's state `vol`, a
chunk's rays, the sky behind them and where a surface stops them, and returns the volume's part:
radiance [n, 3], transmittance, weight sums, median t and entry t [n]."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..geometry.camera import Rays
from ..geometry.rays import clip_to_ray
from ..schema.batch import take
from . import kernel_march
from .composite import VolumePart
from .context import VolumeContext
from .march import march, march_adaptive
from .physical import closed_form
from .skip import macro_grid, occupied_span


def entry_exit(vol, rays: Rays, t_limit: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """(t0, t1, hit) [n] of the rays through the volume, up to `t_limit` [n] where given; where
    the volume marches in a Dr.Jit kernel, its bounds' interval is one too."""
    t_near, t_far = vol.intersect(rays.origins, rays.directions, rays.scene_index, kernel=vol.plan.backend == "drjit")
    if vol.shading.semantics == "shader":  # the seeds: march whenever the exit is ahead, from max(t_near, 0)
        t0, t1 = t_near.clamp_min(0.0), t_far.clamp_max(vol.plan.reach)
        hit = (t_far >= 0) & (t_far >= t_near)
    else:
        t0, t1, hit = clip_to_ray(t_near, t_far, vol.plan.reach)
    if t_limit is not None:
        t1 = torch.minimum(t1, t_limit)
        hit = hit & (t1 > t0)
    return t0, t1, hit


def _counted(ctx: VolumeContext, res):
    """The march result `res`, its steps and truncated rays counted in the render's stats."""
    ctx.counts.march_steps += int(res.steps.sum())
    ctx.counts.truncated_rays += int(res.truncated.sum())
    return res


def _part(ctx: VolumeContext, vol, res, t0: Tensor, hit: Tensor) -> VolumePart:
    radiance, trans = res.radiance, res.transmittance
    if vol.shading.semantics == "shader":  # the template's clamp(sum, 0, 1)
        radiance, trans = radiance.clamp(0.0, 1.0), 1.0 - (1.0 - trans).clamp(0.0, 1.0)
    return VolumePart(radiance=radiance, transmittance=trans, weight_sum=res.weight_sum, weighted_t=res.weighted_t,
                      median_t=res.median_t, t0=torch.where(hit, t0, torch.full_like(t0, math.inf)))


def run_closed_form(ctx: VolumeContext, vol, rays: Rays, background: Tensor | None, t_limit: Tensor | None) -> VolumePart:
    """The volume's part for a chunk's `rays` [n] (the sky behind them `background` [n, 3] or
    None, surfaces at `t_limit` [n] or None) in closed form. -> the part: radiance [n, 3],
    transmittance, weight sums, median t and entry t [n]."""
    t0, t1, hit = entry_exit(vol, rays, t_limit)
    with ctx.timer.section(vol.plan.step_pass):
        return closed_form(ctx, vol, rays, t0, t1, hit)


def run_march(ctx: VolumeContext, vol, rays: Rays, background: Tensor | None, t_limit: Tensor | None, *, skip: bool = False) -> VolumePart:
    """The volume's part for a chunk's `rays` [n] (`background` [n, 3] or None, `t_limit` [n] or
    None) by the fixed march, on the backend the plan chose; `skip`: over the occupied span only.
    -> the part: radiance [n, 3], transmittance, weight sums, median t and entry t [n]."""
    st = ctx.settings
    t0, t1, hit = entry_exit(vol, rays, t_limit)
    occupied, marched = None, hit
    if skip:
        with ctx.timer.section(vol.plan.skip_pass):
            occupied, marched = skipped_span(vol, rays, t0, t1, hit)
    with ctx.timer.section(vol.plan.step_pass):
        if vol.plan.backend == "drjit":  # one Dr.Jit kernel
            if vol.shading.semantics == "shader":
                res = kernel_march.march_look(ctx, vol, rays, background, t0, t1, hit, ctx.dither(rays))
            else:
                res = kernel_march.march(ctx, [vol], rays, background, t0[None], t1[None], marched[None, None],
                                         ctx.dither(rays), occupied=occupied)
            if bool(marched.any()):  # its per-sample passes ran inside the kernel, their time in its own
                for name in vol.plan.sample_passes:
                    with ctx.timer.section(name):
                        pass
            return _part(ctx, vol, res, t0, hit)
        medium = vol.shading.fn(ctx, vol, rays, background)
        res = march(
            t0, t1, marched, medium, rule=st.rule, integrator=st.integrator, semantics=vol.shading.semantics,
            dither=ctx.dither(rays), dither_unit="absolute" if st.dither == "sin" else "step",
            min_transmittance=st.min_transmittance, occupied=occupied,
            compact_below=vol.plan.compact_below,
        )
    return _part(ctx, vol, _counted(ctx, res), t0, hit)


def run_skip(ctx: VolumeContext, vol, rays: Rays, background: Tensor | None, t_limit: Tensor | None) -> VolumePart:
    """`run_march` over the occupied span only (empty space skipped): the same part, radiance
    [n, 3] and the rest [n]."""
    return run_march(ctx, vol, rays, background, t_limit, skip=True)


def run_tolerance(ctx: VolumeContext, vol, rays: Rays, background: Tensor | None, t_limit: Tensor | None) -> VolumePart:
    """The volume's part for a chunk's `rays` [n] (`background` [n, 3] or None, `t_limit` [n] or
    None) by the error-controlled march at `march.tolerance`. -> the part: radiance [n, 3],
    transmittance, weight sums, median t and entry t [n]."""
    st = ctx.settings
    t0, t1, hit = entry_exit(vol, rays, t_limit)
    feature = vol.field.feature_size
    with ctx.timer.section(vol.plan.step_pass):
        medium = vol.shading.fn(ctx, vol, rays, background, signed=True)
        res = march_adaptive(
            t0, t1, hit, medium, tolerance=st.tolerance, integrator=st.integrator,
            radiance_scale=ctx.radiance_scale(rays.scene_index), min_transmittance=st.min_transmittance,
            # a field's detail caps the steps; a smooth one's steps are capped by march.steps
            max_steps_per_span=st.rule.steps if st.rule.placement == "count" and feature is None else None,
            max_step=None if feature is None else 0.5 * take(feature, rays.scene_index),
        )
    ctx.counts.error_estimate = max(ctx.counts.error_estimate, float(res.error.max()) if len(res.error) else 0.0)
    return _part(ctx, vol, _counted(ctx, res), t0, hit)


def skipped_span(vol, rays: Rays, t0: Tensor, t1: Tensor, hit: Tensor):
    """((t_first, t_last), hit) [n]: the span of each ray through the grid's occupied macro
    cells; rays that cross none leave `hit`."""
    first, last = t0.clone(), t1.clone()
    found = torch.zeros_like(hit)
    grid = vol.field.inner
    for b in range(len(vol.params)):
        idx = (hit & (rays.scene_index == b)).nonzero().squeeze(1)
        if idx.numel():
            if b not in vol.macro:
                vol.macro[b] = macro_grid(grid.occupancy(b), grid.box_min[b], grid.box_max[b])
            first[idx], last[idx], found[idx] = occupied_span(
                rays.origins[idx], rays.directions[idx], t0[idx], t1[idx], vol.macro[b], grid.box_min[b])
    return (first, last), hit & found


STRATEGIES = {"closed_form": run_closed_form, "march": run_march, "skip": run_skip, "tolerance": run_tolerance}
