"""The volumetric shadow march: transmittance from points towards a light through one volume."""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor


def shadow_distances(
    exit_distance: Tensor, *, steps: int, growth: float = 1.0, first_step: float | None = None
) -> tuple[Tensor, Tensor]:
    """Midpoints and lengths of the shadow ray's segments towards the light.

    `exit_distance`: [N], where the shadow ray leaves the volume's bounds. Segment lengths grow
    geometrically by `growth`; with `first_step` None they are scaled to end exactly at the exit
    (exact for homogeneous media), otherwise they start at `first_step` and are cut at the exit.
    Returns (midpoints [N, K], lengths [N, K]).
    """
    k = torch.arange(steps, dtype=exit_distance.dtype, device=exit_distance.device)
    rel = growth**k  # [K]
    if first_step is None:
        lengths = exit_distance[:, None] * (rel / rel.sum())[None, :]
    else:
        lengths = first_step * rel[None, :].expand(exit_distance.shape[0], steps)
    ends = torch.cumsum(lengths, dim=1).minimum(exit_distance[:, None])
    starts = torch.cat([torch.zeros_like(ends[:, :1]), ends[:, :-1]], dim=1)
    return 0.5 * (starts + ends), ends - starts


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
