"""Per-medium labels: AOVs computed only when asked for (`render(..., aovs=[...])`, a recipe's
`[dataset] aovs`), each its own pass `labels.<name>` (a label nobody asks for is not planned and
costs nothing). Per ray, after the composite (before the `[atmosphere]` air, which is no medium
here):

- ``optical_thickness`` τ = ∫ σ_t dt along the primary ray through every volume (σ_t = the
  volume's `sigma_t` × density, whichever its shading), up to the surface hit (voxels, terrain) or
  as far as the render marches the volume (its bounds' exit, `march.max_distance`). Homogeneous
  volumes integrated in closed form by the render are exact; the others are a midpoint sum over
  `march.steps` equal segments of each volume's chord (the march's own step count, no dither, no
  early termination: τ is unbounded).
- ``alpha_volumes`` (V channels, scene order): each volume's share of the ray's alpha, from the
  render's own parts composited as the render composites them, in order of entry: volume v's is
  T_before · (1 − T_v), T_before the transmittance of the volumes entered before it. Their sum is
  the ray's alpha where no surface is hit (exactly for any layout, overlaps included: overlapping
  volumes split as the composite orders them).
- ``instance``: the id of what contributed most to the pixel's opacity: the largest of the
  background's remaining transmittance (id 0), each volume's alpha (ids 1..V, scene order) and a
  hit surface's remaining transmittance (voxels: V + the material id, 1.. as the ``material``
  AOV; terrain: V + 1, or V + M + 1 beside voxels of M materials, `surfaces.terrain_id`: the
  surface the ray met first). Integer-valued float32 (the render's buffers), a pixel's first
  sub-sample.
- ``sun_visibility``: the transmittance towards the scene's sun (`Plan.sun`; refused without one) from the
  depth point: where transmittance crosses 0.5 (``depth_median``) or else the surface hit, through
  every volume, whatever its shading, as the lights' shadow rays see them (marched with the sun's
  `shadow` settings, or the quality level's shadow steps), times 0 where the terrain or the voxels
  block it (from a surface hit the ray starts where that surface's own shadow rays do); 1 where
  neither exists (sky).
"""

from __future__ import annotations

from typing import Protocol

import torch
from torch import Tensor

from ..geometry.camera import Rays
from ..geometry.surface_hit import SurfaceHit
from ..scene.model import VoxelShadow
from ..schema.batch import take
from ..volume import kernel_march
from ..volume.composite import Composited, Media, entry_order
from ..volume.context import VolumeContext
from ..volume.density_lanes import writes_in_lanes
from ..volume.strategy import entry_exit
from .plan import Plan
from .surfaces import SurfacesHit, terrain_id


class LabelContext(VolumeContext, Protocol):
    """A render as the labels see it: a `VolumeContext` (whose `terrain` and `voxels` the sun's
    shadow ray meets) with its plan."""

    plan: Plan

    def shadow_rays(self, use, p: Tensor, s: Tensor, direction: Tensor, distance: Tensor) -> Tensor:
        """`shadow.occluder_transmittance` of the shadow rays of LightPass `use` from `p` [n, 3]
        along `direction` [n, 3] up to `distance` [n], as a Dr.Jit kernel where the render runs
        them -> [n]."""


def optical_thickness(ctx: LabelContext, rays: Rays, t_limit: Tensor | None) -> Tensor:
    """τ [n] along the chunk's rays through every volume, up to `t_limit` [n] (a surface hit): each
    volume's midpoint sum as one Dr.Jit kernel where the render runs them and the volume is written
    in lanes (`kernel_march.chord_density`), else eagerly (the reference)."""
    tau = rays.origins.new_zeros(len(rays))
    for vol in ctx.volumes:
        t0, t1, hit = entry_exit(vol, rays, t_limit)
        ids = hit.nonzero().squeeze(1)
        if ids.numel() == 0:
            continue
        s, a, length = rays.scene_index[ids], t0[ids], t1[ids] - t0[ids]
        # homogeneous: σ_t at any point is σ_t everywhere, one sample (the midpoint) is exact
        steps = 1 if vol.plan.strategy == "closed_form" else ctx.settings.rule.steps
        dt = length / steps
        if ctx.plan.kernels and writes_in_lanes(vol):
            acc = kernel_march.chord_density(ctx, vol, rays, a, length, ids, steps)
        else:
            o, d, acc = rays.origins[ids], rays.directions[ids], torch.zeros_like(a)
            for k in range(steps):  # one sample per segment: [n] at a time, whatever the step count
                acc = acc + vol.field(torch.addcmul(o, (a + (k + 0.5) * dt)[:, None], d), s)
        tau[ids] += take(vol.params.sigma_t, s) * acc * dt
    return tau


def volume_alphas(media: Media, volumes: int) -> Tensor:
    """[V, n]: each of the `volumes` volumes' share of the alpha, its parts composited front to back
    in order of entry (`t0`) as `composite_volumes` does: T_before · (1 − T_part) for a part of one
    volume, T_before · its share of the joint march's alpha for a medium marched jointly."""
    trans = torch.stack([p.transmittance for p in media.parts])  # [P, n]
    order = entry_order(media.parts)
    ordered = trans.gather(0, order)
    before = torch.cumprod(torch.cat([torch.ones_like(ordered[:1]), ordered[:-1]]), dim=0)
    before = torch.empty_like(trans).scatter_(0, order, before)
    out = trans.new_zeros(volumes, trans.shape[1])
    for k, members in enumerate(media.members):
        if len(members) == 1:
            out[members[0]] = before[k] * (1.0 - trans[k])
        else:
            out[list(members)] = before[k] * media.shares
    return out


def instance(ctx: LabelContext, alphas: Tensor | None, remaining: Tensor, surf: SurfaceHit | None) -> Tensor:
    """Ids [n] (float): argmax over background (0), volumes (1..V) and the surface (V + material).
    `alphas` [V, n] or None (no volumes); `remaining` [n] the transmittance left behind them."""
    n_vol = 0 if alphas is None else alphas.shape[0]
    hit = torch.zeros_like(remaining, dtype=torch.bool) if surf is None else surf.hit
    background = torch.where(hit, torch.zeros_like(remaining), remaining)
    weights = [background] + ([] if alphas is None else list(alphas)) + [torch.where(hit, remaining, torch.zeros_like(remaining))]
    best = torch.argmax(torch.stack(weights), dim=0)  # ties: the first (background before media)
    surface_id = torch.ones_like(remaining)
    if surf is not None and "material" in surf.aovs:
        surface_id = surf.aovs["material"][:, 0].to(remaining.dtype)
    if isinstance(surf, SurfacesHit):  # voxels and a terrain: the terrain's id where it was met first
        surface_id = torch.where(surf.terrain, torch.full_like(surface_id, terrain_id(ctx.batch)), surface_id)
    ids = best.to(remaining.dtype)
    return torch.where(best == n_vol + 1, n_vol + surface_id, ids)


def surface_lift(ctx: LabelContext, s: Tensor, t: Tensor, on_terrain: Tensor | None = None) -> Tensor:
    """How far [n] along its normal a shadow ray from a surface hit at distance `t` [n] of scenes `s`
    [n] starts, as the surface pass's own: the terrain's `shadow_offset` plus its hit rule's width,
    the voxels' `shadow.offset` (its default without `voxels.shadow`); with both surfaces, the
    terrain's where `on_terrain` [n] (the terrain was met first), else the voxels'."""
    ground = blocks = None
    if ctx.plan.terrain is not None:
        terrain = ctx.batch.terrain
        ground = take(terrain.shadow_offset, s) + 2.0 * take(terrain.epsilon, s) * (1.0 + t)
    if ctx.plan.voxels is not None:
        shadow = ctx.batch.voxels.shadow
        blocks = (torch.full_like(t, VoxelShadow.model_fields["offset"].default) if shadow is None
                  else take(shadow.offset, s))
    if ground is None or blocks is None:
        return blocks if ground is None else ground
    return torch.where(on_terrain, ground, blocks)


def sun_visibility(ctx: LabelContext, rays: Rays, volumes: Composited, surf: SurfaceHit | None) -> Tensor:
    """Transmittance [n] to the scene's sun (`Plan.sun`) from each ray's depth point (1 where it has none)."""
    use = ctx.plan.labels.sun
    s, o, d = rays.scene_index, rays.origins, rays.directions
    t = volumes.median_t
    on_surface = torch.zeros_like(t, dtype=torch.bool)
    if surf is not None:
        on_surface = surf.hit & (t == 0)
        t = torch.where(on_surface, surf.t, t)
    out = torch.ones_like(t)
    ids = (t > 0).nonzero().squeeze(1)
    if ids.numel() == 0:
        return out
    si, ti = s[ids], t[ids]
    p = torch.addcmul(o[ids], ti[:, None], d[ids])
    if surf is not None:  # a surface point's ray starts where the surface's own shadow rays do
        on_terrain = surf.terrain[ids] if isinstance(surf, SurfacesHit) else None
        lift = surface_lift(ctx, si, ti, on_terrain) * on_surface[ids].to(t.dtype)
        p = p + lift[:, None] * surf.aovs["normal"][ids]
    direction = take(ctx.lights[ctx.plan.sun].direction, si)
    distance = torch.full_like(ti, torch.inf)
    # the volumes, the terrain (`use.terrain`) and the voxels (`use.voxels`: the same DDA shadow ray)
    out[ids] = ctx.shadow_rays(use, p, si, direction, distance)
    return out


def per_ray(ctx: LabelContext, rays: Rays, media: Media, volumes: Composited, surf: SurfaceHit | None) -> dict[str, Tensor]:
    """The planned labels of a chunk's rays, each [n, C], from the render's volume parts `media`,
    their composite `volumes` and the surface pass's result `surf`."""
    names, out = ctx.plan.labels.names, {}
    if "optical_thickness" in names:
        with ctx.timer.section("labels.optical_thickness"):
            out["optical_thickness"] = optical_thickness(ctx, rays, None if surf is None else surf.t)[:, None]
    alphas = None
    if media.parts and ("alpha_volumes" in names or "instance" in names):
        with ctx.timer.section("labels.alpha_volumes" if "alpha_volumes" in names else "labels.instance"):
            alphas = volume_alphas(media, len(ctx.volumes))
        if "alpha_volumes" in names:
            out["alpha_volumes"] = alphas.T
    if "instance" in names:
        with ctx.timer.section("labels.instance"):
            out["instance"] = instance(ctx, alphas, volumes.transmittance, surf)[:, None]
    if "sun_visibility" in names:
        with ctx.timer.section("labels.sun_visibility"):
            out["sun_visibility"] = sun_visibility(ctx, rays, volumes, surf)[:, None]
    return out
