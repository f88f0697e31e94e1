"""Post-processing of images (B, 3, H, W): the `POST` registry, applied in registration order.

Each effect is its function `fn(x (B, 3, H, W), post (Stacked), aovs) -> x` and two capabilities:
``active(post) -> bool`` (the effect runs only where some scene of the batch asks for it; at its
identity setting it costs nothing) and ``pass_name(post) -> str`` (its name in `stats`). Per-scene
values (exposure, vignette strength, smoothstep edges, fog colour and density) arrive as (B, ...)
tensors, so each image of a batch gets its own.
"""

from __future__ import annotations

from typing import Literal

import torch
from pydantic import Field, field_validator
from torch import Tensor

from .mathops import pow_
from .registry import Registry
from .schema import Strict, Vec3, nonneg


class Fog(Strict):
    """Distance fog: mix(radiance, color, 1 − e^{−density · distance}) by the expected distance of
    what each ray hit (volumes and voxel surfaces); rays that hit nothing are left alone."""

    color: Vec3 = (0.5, 0.6, 0.7)
    density: float = Field(0.01, ge=0.0)
    _c = field_validator("color")(lambda v: nonneg(v))


class Post(Strict):
    tonemap: Literal["none", "smoothstep", "reinhard", "aces"] = "none"
    exposure: float = Field(1.0, gt=0.0)
    smoothstep_edges: tuple[float, float] = (0.15, 1.1)
    vignette: float = Field(0.0, ge=0.0, le=1.0)
    fog: Fog | None = None

    @field_validator("smoothstep_edges")
    @classmethod
    def _edges(cls, v):
        if v[1] <= v[0]:
            raise ValueError("smoothstep_edges must be increasing")
        return v


def _per_image(v: Tensor) -> Tensor:
    """(B,) -> (B, 1, 1, 1): one value per image."""
    return v[:, None, None, None]


def smoothstep(edge0: Tensor | float, edge1: Tensor | float, x: Tensor) -> Tensor:
    """GLSL smoothstep: t = clamp((x − e0)/(e1 − e0), 0, 1); t²(3 − 2t)."""
    t = ((x - edge0) / (edge1 - edge0)).clamp(0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def reinhard(x: Tensor) -> Tensor:
    """x / (1 + x), for x ≥ 0."""
    return x / (1.0 + x)


def aces(x: Tensor) -> Tensor:
    """Narkowicz's ACES filmic fit, clamped to [0, 1]."""
    return ((x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14)).clamp(0.0, 1.0)


def vignette(image: Tensor, strength: Tensor | float) -> Tensor:
    """The seeds' 0.25 + 0.75·(16 u v (1−u)(1−v))^0.1 at pixel centres, mixed in by `strength`
    ((B,) or a number). `image`: (B, C, H, W)."""
    _, _, h, w = image.shape
    u = (torch.arange(w, dtype=image.dtype, device=image.device) + 0.5) / w
    v = (torch.arange(h, dtype=image.dtype, device=image.device) + 0.5) / h
    shape = 16.0 * (v * (1 - v))[:, None] * (u * (1 - u))[None, :]
    factor = 0.25 + 0.75 * pow_(shape, 0.1)
    strength = _per_image(torch.as_tensor(strength, dtype=image.dtype, device=image.device).expand(image.shape[0]))
    return image * torch.lerp(torch.ones_like(factor), factor, strength)


def distance_fog(radiance: Tensor, distance: Tensor, color: Tensor, density: Tensor) -> Tensor:
    """mix(radiance, fog colour, 1 − e^{−density·distance}) where something was hit (distance > 0).
    `radiance`: (B, 3, H, W); `distance`: (B, 1, H, W); `color`: (B, 3); `density`: (B,)."""
    amount = -torch.expm1(-_per_image(density) * distance)
    return torch.lerp(radiance, color[:, :, None, None].expand_as(radiance), amount)


TONEMAPS = {
    "smoothstep": lambda x, post: smoothstep(_per_image(post.smoothstep_edges[:, 0]), _per_image(post.smoothstep_edges[:, 1]), x),
    "reinhard": lambda x, post: reinhard(x.clamp_min(0.0)),
    "aces": lambda x, post: aces(x.clamp_min(0.0)),
}

POST = Registry("post")
POST.register("fog", Fog, lambda x, post, aovs: distance_fog(x, aovs["distance"], post.fog.color, post.fog.density),
              active=lambda post: post.fog is not None, pass_name=lambda post: "post.fog")
POST.register("exposure", float, lambda x, post, aovs: x * _per_image(post.exposure),
              active=lambda post: bool((post.exposure != 1.0).any()), pass_name=lambda post: "post.exposure")
POST.register("tonemap", str, lambda x, post, aovs: TONEMAPS[post.tonemap](x, post),
              active=lambda post: post.tonemap != "none", pass_name=lambda post: f"post.tonemap.{post.tonemap}")
POST.register("vignette", float, lambda x, post, aovs: vignette(x, post.vignette),
              active=lambda post: bool((post.vignette > 0).any()), pass_name=lambda post: "post.vignette")
