"""Compositing a ray's parts front to back: the volumes it crosses (in the order it enters them),
then what lies behind them (a voxel surface, or the sky), into radiance, alpha and the depth
labels. Plain functions of per-ray tensors [n]."""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from torch import Tensor

from ..geometry.surface_hit import SurfaceHit


@dataclass(frozen=True)
class Composited:
    """Volumes along a chunk's rays [n], composited: radiance [n, 3], transmittance, the depth
    weights' sum Σwᵢ and Σwᵢtᵢ, and the median depth t (0: transmittance never crossed 0.5), [n]."""

    radiance: Tensor
    transmittance: Tensor
    weight_sum: Tensor
    weighted_t: Tensor
    median_t: Tensor


@dataclass(frozen=True)
class VolumePart(Composited):
    """One volume's part of a chunk's rays (what a strategy returns), with the distance `t0` [n]
    where each ray enters it (inf: it does not)."""

    t0: Tensor


@dataclass(frozen=True)
class Media:
    """The parts of a chunk's rays that the volumes were marched into: `parts` (any order; the
    composite orders them per ray by entry), `members` the volumes each holds (scene indices: one,
    or the joint march's), and `shares` [M, n], the joint part's alpha split among its M members
    (None: no joint part, or its shares not asked for)."""

    parts: list[VolumePart]
    members: list[tuple[int, ...]]
    shares: Tensor | None = None


PART_KEYS = tuple(f.name for f in fields(Composited))


def entry_order(parts: list[VolumePart]) -> Tensor:
    """[V, n]: per ray, the parts' indices front to back by entry `t0` (the composite's order)."""
    return torch.argsort(torch.stack([p.t0 for p in parts]), dim=0)


def _in_entry_order(parts: list[VolumePart]) -> dict[str, Tensor]:
    """Each of the parts' `PART_KEYS` stacked [V, n] (or [V, n, 3]) front to back per ray; one
    part as it is (nothing to order: the sort and gathers were ~2 ms of a 256² render)."""
    if len(parts) < 2:
        return {key: getattr(parts[0], key)[None] for key in PART_KEYS} if parts else {}
    order = entry_order(parts)
    ordered = {}
    for key in PART_KEYS:
        stacked = torch.stack([getattr(p, key) for p in parts])
        index = order.view(*order.shape, *([1] * (stacked.dim() - 2))).expand_as(stacked)
        ordered[key] = stacked.gather(0, index)
    return ordered


def composite_volumes(parts: list[VolumePart], like: Tensor) -> Composited:
    """Front-to-back composite of volume parts (each: radiance [n, 3], transmittance, weight_sum,
    weighted_t, median_t and entry t0 [n]), ordered per ray by entry. `like`: [n] (dtype, device).
    -> radiance [n, 3] (or the parts' [n, C]), transmittance, weight_sum, weighted_t and median_t
    [n] of the whole ray."""
    radiance = like.new_zeros(like.shape[0], parts[0].radiance.shape[1] if parts else 3)
    trans = torch.ones_like(like)
    wsum, wt, median = torch.zeros_like(trans), torch.zeros_like(trans), torch.zeros_like(trans)
    ordered = _in_entry_order(parts)
    for k in range(len(parts)):
        part_trans = ordered["transmittance"][k]
        radiance = radiance + trans[:, None] * ordered["radiance"][k]
        wsum = wsum + trans * ordered["weight_sum"][k]
        wt = wt + trans * ordered["weighted_t"][k]
        crossed = (median == 0) & (trans > 0.5) & (trans * part_trans <= 0.5)
        median = torch.where(crossed, ordered["median_t"][k], median)
        trans = trans * part_trans
    return Composited(radiance=radiance, transmittance=trans, weight_sum=wsum, weighted_t=wt, median_t=median)


def finish(volumes: Composited, behind: Tensor | None, surface: SurfaceHit | None, forward_cos: Tensor,
           depth_threshold: float) -> dict[str, Tensor]:
    """The ray's outputs from its composited volumes, what lies behind them (`behind` [n, 3]: the
    shaded surface where one was hit, else the sky; None: black) and the surface pass's result
    (hit, t [n] and its AOVs; None without voxels). Depth is planar (distance × `forward_cos` [n]);
    volume depth is the expected termination depth where alpha ≥ `depth_threshold`, and a surface
    is an opaque terminal weight T at its distance."""
    trans, wsum, wt, median = volumes.transmittance, volumes.weight_sum, volumes.weighted_t, volumes.median_t
    radiance = volumes.radiance if behind is None else volumes.radiance + trans[:, None] * behind
    alpha = 1.0 - trans
    tiny = torch.finfo(wsum.dtype).tiny
    distance = torch.where(wsum > 0, wt / wsum.clamp_min(tiny), torch.zeros_like(wsum))
    valid = (alpha >= depth_threshold) & (wsum > 0)
    distance = torch.where(valid, distance, torch.zeros_like(distance))
    extra = {}
    if surface is not None:
        hit, ts = surface.hit, torch.where(surface.hit, surface.t, torch.zeros_like(trans))
        denom = (wsum + trans).clamp_min(tiny)
        distance = torch.where(hit, (wt + trans * ts) / denom, distance)
        median = torch.where(hit & (median == 0), ts, median)
        alpha = torch.where(hit, torch.ones_like(alpha), alpha)
        extra = surface.aovs
    return dict(radiance=radiance, alpha=alpha, depth=distance * forward_cos, distance=distance,
                depth_median=median * forward_cos, **extra)
