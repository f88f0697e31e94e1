"""The volumetric shadow march: transmittance from points towards a light through one volume,
and through everything else a shadow or sky-visibility ray meets (`occluder_transmittance`: the
other volumes, whatever their shading, and the terrain)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Callable

import torch
from torch import Tensor

from ..fields import DENSITIES
from ..geometry.rays import clip_to_ray
from ..ops import lanes
from ..schema.batch import take
from .context import VolumeContext
from .density_lanes import inner_and_edge, sun_grid_kernel, writes_in_lanes
from .sun_volume import SunGrid, grid_atlas, grid_layout, sun_grid


def shadow_segments(exit_distance, *, steps: int, growth: float = 1.0, first_step: float | None = None) -> list:
    """Midpoints and lengths of the shadow ray's segments towards the light, lanes (`ops.lanes`).

    `exit_distance`: where the shadow ray leaves the volume's bounds. Segment lengths grow
    geometrically by `growth`; with `first_step` None they are scaled to end exactly at the exit
    (exact for homogeneous media), otherwise they start at `first_step` and are cut at the exit.
    Returns [(midpoint, length)] of the `steps` segments, each a lane.
    """
    out, start = [], lanes.full_like(exit_distance, 0.0)
    for reach in segment_reach(steps=steps, growth=growth, first_step=first_step):
        end = segment_end(exit_distance, reach, first_step)
        out.append((0.5 * (start + end), end - start))
        start = end
    return out


def segment_reach(*, steps: int, growth: float = 1.0, first_step: float | None = None) -> list[float]:
    """Where each of `shadow_segments`' segments ends, before the cut at the exit: a fraction of
    the exit distance (`first_step` None) or a distance."""
    rel = [growth**k for k in range(steps)]
    total = sum(rel)
    out, reach = [], 0.0
    for k in range(steps):
        reach = reach + (rel[k] / total if first_step is None else first_step * rel[k])
        out.append(reach)
    return out


def segment_end(exit_distance, reach, first_step: float | None):
    """A segment's end (lanes) from its `segment_reach` value `reach` (a number, or a lane of them)."""
    return lanes.minimum(exit_distance * reach if first_step is None else reach, exit_distance)


def shadow_distances(
    exit_distance: Tensor, *, steps: int, growth: float = 1.0, first_step: float | None = None
) -> tuple[Tensor, Tensor]:
    """`shadow_segments` as tensors: `exit_distance` [N] -> (midpoints [N, K], lengths [N, K])."""
    segments = shadow_segments(exit_distance, steps=steps, growth=growth, first_step=first_step)
    return torch.stack([m for m, _ in segments], dim=1), torch.stack([dt for _, dt in segments], dim=1)


def shadow_transmittance(
    points: Tensor,
    light_dir: Tensor,
    exit_distance: Tensor,
    extinction: Callable[[Tensor, Tensor], Tensor],
    *,
    steps: int,
    growth: float = 1.0,
    first_step: float | None = None,
) -> Tensor:
    """Transmittance from each point towards the light, marched through one volume.

    `points`, `light_dir`: [N, 3]; `exit_distance`: [N]; `extinction(points [M,3], owner [M]) ->
    σ_t [M]` where `owner` indexes the N shadow rays. Returns [N]."""
    mid, length = shadow_distances(exit_distance, steps=steps, growth=growth, first_step=first_step)
    n, k = mid.shape
    sample_points = points[:, None, :] + mid[..., None] * light_dir[:, None, :]  # [N, K, 3]
    owner = torch.arange(n, device=points.device).repeat_interleave(k)
    sigma = extinction(sample_points.reshape(-1, 3), owner).reshape(n, k)
    return torch.exp(-(sigma * length).sum(dim=1))


def line_depth(vol, p: Tensor, s: Tensor, direction: Tensor, length: Tensor, start: Tensor | None = None) -> Tensor:
    """∫ density along `length` [n] of the lines from `p` [n, 3] (scenes `s` [n]) along `direction`
    [n, 3] through volume `vol`, in closed form (`vol.plan.line_integral`: its kind's
    ``optical_depth``): from its density at `p` (`start` [n], the sample's own; None: evaluated
    there, one evaluation, counted) and the profile's analytic factor. -> [n] (σ_t not applied)."""
    inner, _ = inner_and_edge(vol)
    kind = DENSITIES[vol.params.density.kind].caps
    q = kind["lanes"][0](inner, SimpleNamespace(per_lane=lambda v: lanes.columns(take(v, s))))
    return kind["optical_depth"](q, vol.field(p, s) if start is None else start, direction.unbind(1), length)


def occluder_transmittance(ctx: VolumeContext, use, p: Tensor, s: Tensor, direction: Tensor, distance: Tensor) -> Tensor:
    """What a shadow ray of LightPass `use` (or a sky-visibility ray: `use.light` None) from `p`
    [n, 3] along `direction` [n, 3], up to `distance` [n] (inf: a sun, the sky), lets through
    besides its own volume: each volume `use.occluders` names (σ_t = its `sigma_t` × density,
    whatever its shading), marched over its chord in `use.shadow.steps` equal steps (exact for homogeneous media)
    or, with `shadow.method = "grid"`, looked up in that volume's sun grid where the ray enters
    it (a volume whose plan has a `line_integral`: that, exact, either way), times 0 where the terrain blocks it (`use.terrain`) and where the voxels do (`use.voxels`)
    -> [n]. The terrain's and the voxels' visibility (0 or 1) come first: a volume is marched only
    where they let light through. Each is its own pass, reported only where some shadow ray crosses it."""
    # the blockers first: a volume is marched only where the terrain and the voxels let light through
    out = p.new_ones(p.shape[0])
    if use.terrain:
        with ctx.timer.section(f"{use.name}.terrain"):
            out = out * ctx.terrain.visibility(p, direction, s, distance)
    if use.voxels:
        with ctx.timer.section(f"{use.name}.voxels"):
            out = out * ctx.voxels.visibility(p, direction, s, distance)
    for j in use.occluders:
        other = ctx.volumes[j]
        t0, t1, crosses = clip_to_ray(*other.intersect(p, direction, s), torch.minimum(distance, p.new_tensor(other.plan.reach)))
        ids = (crosses & (out > 0)).nonzero().squeeze(1)
        if ids.numel() == 0:
            continue
        with ctx.timer.section(f"{use.name}.volume{j}"):
            sj, entry = s[ids], torch.addcmul(p[ids], t0[ids, None], direction[ids])
            if other.plan.line_integral:  # exact, from its density where the ray enters it
                through = torch.exp(-take(other.params.sigma_t, sj) * line_depth(other, entry, sj, direction[ids], t1[ids] - t0[ids]))
            elif use.shadow.method == "grid":  # the other volume's sun grid, looked up where the ray enters it
                sigma = take(other.params.sigma_t, sj) * other.field(entry, sj)
                through = sun_grids(ctx, other, use.light).lookup(entry, sigma, sj)
            else:
                through = shadow_transmittance(
                    entry, direction[ids], t1[ids] - t0[ids],
                    lambda q, owner: take(other.params.sigma_t, sj[owner]) * other.field(q, sj[owner]), steps=use.shadow.steps)
            out[ids] = out[ids] * through
    return out


def sun_grids(ctx: VolumeContext, vol, light: int) -> SunGrid:
    """Transmittance to sun `light` through the volume, a table per scene of the batch, built on
    first use and kept for every chunk of the render: as one Dr.Jit kernel where the plan runs
    kernels and the volume is written in lanes (`density_lanes.sun_grid_kernel`), else eagerly
    (`sun_volume.grid_atlas`, the reference)."""
    if light not in vol.sun_grids:
        resolution = ctx.lights[light].params.shadow.resolution
        direction = ctx.lights[light].direction
        lo, hi = vol.bounds.aabb(vol.params.bounds.value)

        def owner(q: Tensor, b: int) -> Tensor:
            return torch.full((q.shape[0],), b, dtype=torch.long, device=q.device)

        layouts = [grid_layout(lo[b], hi[b], direction[b], resolution=resolution,
                               chord=lambda o, d, b=b: vol.intersect(o, d, owner(o, b))) for b in range(len(vol.params))]
        if ctx.plan.kernels and writes_in_lanes(vol):
            atlas, evals = sun_grid_kernel(vol, layouts)
            ctx.counts.density_evals += evals
            vol.field.evals += evals
        else:  # (the field counts its evaluations; called on nodes inside the bounds only)
            atlas = torch.cat([grid_atlas(lambda q, b=b: vol.params.sigma_t[b] * vol.field(q, owner(q, b)), layout)
                               for b, layout in enumerate(layouts)])
        vol.sun_grids[light] = sun_grid(layouts, atlas)
    return vol.sun_grids[light]
