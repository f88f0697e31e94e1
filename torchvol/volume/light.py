"""Lighting of a medium: phase functions, the volumetric shadow march, the derivative light.

Physical phase functions are normalised over the sphere (∫ p dω = 1, HG includes 1/4π) and take
cos θ = dot(ray direction, sun direction) with the sun direction pointing towards the sun, so g > 0
is bright looking towards the sun. (The seeds' ``HenyeyGreenstein(dot(rd, -sundir))`` uses the
opposite sign with their sun directions and peaks looking away from the sun.)
"""

from __future__ import annotations

import math
from typing import Callable

import torch
from torch import Tensor

INV_4PI = 1.0 / (4.0 * math.pi)


def isotropic(cos_theta: Tensor) -> Tensor:
    """1/4π. `cos_theta`: [N]."""
    return torch.full_like(cos_theta, INV_4PI)


def henyey_greenstein(cos_theta: Tensor, g: Tensor | float) -> Tensor:
    """(1 − g²) / (4π (1 + g² − 2g cos θ)^{3/2}). `cos_theta`: [N]; `g`: [N] or scalar, |g| < 1.

    The denominator is evaluated as `_hg_base`: no cancellation for g → ±1 at either peak."""
    g = torch.as_tensor(g, dtype=cos_theta.dtype, device=cos_theta.device)
    denom = _hg_base(cos_theta, g)
    return INV_4PI * (1.0 - g) * (1.0 + g) / (denom * denom.sqrt())


def _hg_base(cos_theta: Tensor, g: Tensor) -> Tensor:
    """1 + g² − 2g cos θ written (1 − |g|)² + 2|g|(1 − sign(g) cos θ): both terms ≥ 0, so the
    peak value (1 − |g|)² (cos θ = sign g) has no cancellation for either sign of g."""
    a = g.abs()
    base = (1.0 - a) ** 2 + 2.0 * a * (1.0 - torch.copysign(torch.ones_like(g), g) * cos_theta)
    return base.clamp_min(torch.finfo(cos_theta.dtype).tiny)


def dual_henyey_greenstein(cos_theta: Tensor, g_forward, g_backward, weight) -> Tensor:
    """mix(HG(g_forward), HG(g_backward), weight), the seeds' dual lobe. Arguments: [N] or scalar."""
    return torch.lerp(
        henyey_greenstein(cos_theta, g_forward),
        henyey_greenstein(cos_theta, g_backward),
        torch.as_tensor(weight, dtype=cos_theta.dtype, device=cos_theta.device),
    )


def rayleigh(cos_theta: Tensor) -> Tensor:
    """3/(16π) (1 + cos² θ). `cos_theta`: [N]."""
    return (3.0 / (16.0 * math.pi)) * (1.0 + cos_theta * cos_theta)


def mie_cornette_shanks(cos_theta: Tensor, g: Tensor | float) -> Tensor:
    """Cornette-Shanks Mie approximation 3(1−g²)(1+c²) / (8π(2+g²)(1+g²−2gc)^{3/2}), normalised."""
    g = torch.as_tensor(g, dtype=cos_theta.dtype, device=cos_theta.device)
    denom = _hg_base(cos_theta, g)
    return (3.0 / (8.0 * math.pi)) * (1.0 - g) * (1.0 + g) * (1.0 + cos_theta**2) / ((2.0 + g * g) * denom * denom.sqrt())


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


def derivative_light(density: Tensor, density_towards_light: Tensor, *, scale: Tensor | float) -> Tensor:
    """The seeds' directional-derivative light: clamp((d − d(p + o·L)) / scale, 0, 1).

    `density`, `density_towards_light`: [N]; `scale`: [N] or scalar. -> [N]."""
    return ((density - density_towards_light) / scale).clamp(0.0, 1.0)

