"""Compositing a ray's parts front to back: the volumes it crosses (in the order it enters them),
then what lies behind them (a voxel surface, or the sky), into radiance, alpha and the depth
labels. Plain functions of per-ray tensors [n]."""

from __future__ import annotations

import torch
from torch import Tensor

from ..geometry.surface_hit import SurfaceHit

PART_KEYS = ("radiance", "transmittance", "weight_sum", "weighted_t", "median_t")


def entry_order(parts: list[dict[str, Tensor]]) -> Tensor:
    """[V, n]: per ray, the parts' indices front to back by entry `t0` (the composite's order)."""
    return torch.argsort(torch.stack([p["t0"] for p in parts]), dim=0)


def composite_volumes(parts: list[dict[str, Tensor]], like: Tensor) -> dict[str, Tensor]:
    """Front-to-back composite of volume parts (each: radiance [n, 3], transmittance, weight_sum,
    weighted_t, median_t and entry t0 [n]), ordered per ray by entry. `like`: [n] (dtype, device).
    -> radiance [n, 3], transmittance, weight_sum, weighted_t and median_t [n] of the whole ray."""
    radiance = like.new_zeros(like.shape[0], 3)
    trans = torch.ones_like(like)
    wsum, wt, median = torch.zeros_like(trans), torch.zeros_like(trans), torch.zeros_like(trans)
    if parts:
        order = entry_order(parts)
        ordered = {}
        for key in PART_KEYS:
            stacked = torch.stack([p[key] for p in parts])  # [V, n] or [V, n, 3]
            index = order.view(*order.shape, *([1] * (stacked.dim() - 2))).expand_as(stacked)
            ordered[key] = stacked.gather(0, index)
        for k in range(len(parts)):
            part_trans = ordered["transmittance"][k]
            radiance = radiance + trans[:, None] * ordered["radiance"][k]
            wsum = wsum + trans * ordered["weight_sum"][k]
            wt = wt + trans * ordered["weighted_t"][k]
            crossed = (median == 0) & (trans > 0.5) & (trans * part_trans <= 0.5)
            median = torch.where(crossed, ordered["median_t"][k], median)
            trans = trans * part_trans
    return dict(radiance=radiance, transmittance=trans, weight_sum=wsum, weighted_t=wt, median_t=median)


def finish(volumes: dict[str, Tensor], behind: Tensor | None, surface: SurfaceHit | None, forward_cos: Tensor,
           depth_threshold: float) -> dict[str, Tensor]:
    """The ray's outputs from its composited volumes, what lies behind them (`behind` [n, 3]: the
    shaded surface where one was hit, else the sky; None: black) and the surface pass's result
    (hit, t [n] and its AOVs; None without voxels). Depth is planar (distance × `forward_cos` [n]);
    volume depth is the expected termination depth where alpha ≥ `depth_threshold`, and a surface
    is an opaque terminal weight T at its distance."""
    trans, wsum, wt, median = (volumes[k] for k in ("transmittance", "weight_sum", "weighted_t", "median_t"))
    radiance = volumes["radiance"] if behind is None else volumes["radiance"] + trans[:, None] * behind
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
