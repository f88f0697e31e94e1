"""Post-processing on images (B, 3, H, W): exposure, tonemaps, vignette, distance fog."""

from __future__ import annotations

import torch
from torch import Tensor


def smoothstep(edge0: float, edge1: float, x: Tensor) -> Tensor:
    """GLSL smoothstep: t = clamp((x − e0)/(e1 − e0), 0, 1); t²(3 − 2t)."""
    t = ((x - edge0) / (edge1 - edge0)).clamp(0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def reinhard(x: Tensor) -> Tensor:
    """x / (1 + x), for x ≥ 0."""
    return x / (1.0 + x)


def aces(x: Tensor) -> Tensor:
    """Narkowicz's ACES filmic fit, clamped to [0, 1]."""
    return ((x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14)).clamp(0.0, 1.0)


def vignette(image: Tensor, strength: float) -> Tensor:
    """The seeds' 0.25 + 0.75·(16 u v (1−u)(1−v))^0.1 at pixel centres, mixed in by `strength`.
    `image`: (B, C, H, W)."""
    _, _, h, w = image.shape
    u = (torch.arange(w, dtype=image.dtype, device=image.device) + 0.5) / w
    v = (torch.arange(h, dtype=image.dtype, device=image.device) + 0.5) / h
    shape = 16.0 * (v * (1 - v))[:, None] * (u * (1 - u))[None, :]
    factor = 0.25 + 0.75 * shape.pow(0.1)
    return image * torch.lerp(torch.ones_like(factor), factor, strength)


def distance_fog(radiance: Tensor, distance: Tensor, color: Tensor, density: Tensor) -> Tensor:
    """mix(radiance, fog colour, 1 − e^{−density·distance}) where something was hit (distance > 0).
    `radiance`: (B, 3, H, W); `distance`: (B, 1, H, W); `color`: (B, 3); `density`: (B,)."""
    amount = -torch.expm1(-density[:, None, None, None] * distance)
    return torch.lerp(radiance, color[:, :, None, None].expand_as(radiance), amount)
