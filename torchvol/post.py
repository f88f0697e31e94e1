"""Post-processing of images (B, 3, H, W): the `POST` registry, applied in registration order.

Each effect is its function `fn(x (B, 3, H, W), post (Stacked), aovs) -> x` and its capabilities:
``active(post) -> bool`` (the effect runs only where some scene of the batch asks for it; at its
identity setting it costs nothing), ``pass_name(post) -> str`` (its name in `stats`) and ``view``
(the effect also needs the camera, the sun and the alpha of the frame: it is called with a fourth
argument, a `View`). Per-scene
values (exposure, vignette strength, smoothstep edges, fog colour and density) arrive as (B, ...)
tensors, so each image of a batch gets its own.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from pydantic import Field, field_validator
from torch import Tensor

from .geometry.camera import Camera
from .ops.mathops import pow_, smoothstep
from .schema.models import Strict, Vec3, nonneg
from .schema.registry import Registry


class Fog(Strict):
    """Distance fog: mix(radiance, color, 1 − e^{−density · distance}) by the expected distance of
    what each ray hit (volumes and voxel surfaces); rays that hit nothing are left alone."""

    color: Vec3 = (0.5, 0.6, 0.7)
    density: float = Field(0.01, ge=0.0)
    _c = field_validator("color")(lambda v: nonneg(v))


class GodRays(Strict):
    """Screen-space light shafts (GPU Gems 3 ch. 13, the seeds' post-process god rays): each pixel
    sums `samples` taps of the light sources on its way towards the sun's projected position,
    covering `density` of the way, tap i weighted by `weight` · decay^i; the sum times `exposure`
    times max(0, view · sun) is added to the radiance. The light sources are what the sky shows
    unoccluded, (1 − alpha) · radiance, weighted by max(0, cos(angle to the sun))^`power` so that
    only the sky around the sun shines. Needs lights[0] to be a sun."""

    samples: int = Field(64, ge=1, le=1024)
    density: float = Field(0.9, gt=0.0, le=1.0)
    decay: float = Field(0.97, gt=0.0, le=1.0)
    weight: float = Field(0.05, ge=0.0)
    exposure: float = Field(1.0, ge=0.0)
    power: float = Field(16.0, gt=0.0)


class Post(Strict):
    tonemap: Literal["none", "smoothstep", "reinhard", "aces"] = "none"
    exposure: float = Field(1.0, gt=0.0)
    smoothstep_edges: tuple[float, float] = (0.15, 1.1)
    vignette: float = Field(0.0, ge=0.0, le=1.0)
    fog: Fog | None = None
    god_rays: GodRays | None = None

    @field_validator("smoothstep_edges")
    @classmethod
    def _edges(cls, v):
        if v[1] <= v[0]:
            raise ValueError("smoothstep_edges must be increasing")
        return v


def _per_image(v: Tensor) -> Tensor:
    """(B,) -> (B, 1, 1, 1): one value per image."""
    return v[:, None, None, None]


def reinhard(x: Tensor) -> Tensor:
    """x / (1 + x), for x ≥ 0."""
    return x / (1.0 + x)


def aces(x: Tensor) -> Tensor:
    """Narkowicz's ACES filmic fit, clamped to [0, 1]. It reaches 1 at x ≈ 7.24, so x is taken at
    most 1e4 first: the same values, where x² of a radiance past ~1e19 overflowed float32 to inf/inf."""
    x = x.clamp(max=1e4)
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


@dataclass(frozen=True)
class View:
    """What a `view` post effect sees of the frame besides its AOVs: the `camera`, the direction
    towards the first light `sun` (B, 3) (None when it is not a sun) and `alpha` (B, 1, H, W)."""

    camera: Camera
    sun: Tensor | None
    alpha: Tensor


def _mat_vec(m: Tensor, v: Tensor) -> Tensor:
    """m (B, 3, 3) times v (B, ..., 3) -> (B, ..., 3), written out term by term: a batched matmul's
    rounding may depend on the batch's shape, and a scene must render the same alone or batched."""
    m = m.reshape(m.shape[0], *([1] * (v.dim() - 2)), 3, 3)
    return m[..., 0] * v[..., :1] + m[..., 1] * v[..., 1:2] + m[..., 2] * v[..., 2:]


def sun_on_screen(camera: Camera, sun: Tensor, dtype: torch.dtype) -> tuple[Tensor, Tensor, Tensor]:
    """The sun `sun` (B, 3, towards it, any length) seen by `camera` -> (its pixel position (B, 2),
    column then row, where it projects (finite, arbitrary where it is behind the camera); its unit
    direction in camera axes (B, 3); the cosine between it and the view direction (B,), ≤ 0 where
    the sun is behind the camera)."""
    d = _mat_vec(camera.rotation.to(dtype), sun.to(dtype))
    d = d / d.norm(dim=1, keepdim=True)
    facing = d[:, 2]
    z = torch.where(facing > 1e-6, facing, torch.ones_like(facing))  # no division by ~0 behind the camera
    xy = _mat_vec(camera.K.to(dtype), d)[:, :2] / z[:, None]
    return xy.clamp(-1e6, 1e6), d, facing


def _pixels(h: int, w: int, dtype, device) -> Tensor:
    """(H, W, 2) pixel centres (column, row), as K sees them."""
    col = torch.arange(w, dtype=dtype, device=device)
    row = torch.arange(h, dtype=dtype, device=device)
    return torch.stack(torch.broadcast_tensors(col[None, :], row[:, None]), dim=-1)


def radial_blur(source: Tensor, center: Tensor, *, samples: int, density: Tensor, decay: Tensor, weight: Tensor) -> Tensor:
    """GPU Gems 3 ch. 13's light-shaft sum: for each pixel, its own `source` (B, C, H, W) value plus
    `samples` bilinear taps at pix − i · (pix − center) · density / samples (i = 1..samples), tap i
    weighted by weight · decay^(i−1); taps past the image edge read 0. `center` (B, 2) pixels
    (column, row; pixel centres at integers); `density`, `decay`, `weight` (B,)."""
    _, _, h, w = source.shape
    dtype, dev = source.dtype, source.device
    pix = _pixels(h, w, dtype, dev)
    step = (pix[None] - center[:, None, None]) * (density / samples)[:, None, None, None]  # (B, H, W, 2)
    size = torch.tensor([w, h], dtype=dtype, device=dev)  # grid_sample's [−1, 1] spans the image's outer edges
    start, step = (2.0 * pix + 1.0) / size - 1.0, 2.0 * step / size
    total, fade = source, torch.ones_like(decay)
    for i in range(1, samples + 1):
        tap = F.grid_sample(source, start - i * step, mode="bilinear", padding_mode="zeros", align_corners=False)
        total = total + tap * _per_image(fade * weight)
        fade = fade * decay
    return total


def god_rays(image: Tensor, params, view: View) -> Tensor:
    """Screen-space god rays (see `GodRays`) added to linear radiance `image` (B, 3, H, W); `params`
    the stacked `god_rays` table ((B,) tensors, `samples` shared). Scenes whose sun is behind the
    camera are returned unchanged; samples past the image edge read black."""
    b, _, h, w = image.shape
    dtype, dev = image.dtype, image.device
    sun_xy, sun_cam, facing = sun_on_screen(view.camera, view.sun, dtype)
    pix = _pixels(h, w, dtype, dev)
    # light sources: the unoccluded sky near the sun; cos from each pixel's ray in camera axes
    rays = torch.cat([pix, torch.ones(h, w, 1, dtype=dtype, device=dev)], dim=-1)  # (H, W, 3)
    rays = _mat_vec(torch.linalg.inv(view.camera.K.to(dtype)), rays.expand(b, h, w, 3))
    rays = rays / rays.norm(dim=-1, keepdim=True)
    cos = (rays[..., 0] * sun_cam[:, None, None, 0] + rays[..., 1] * sun_cam[:, None, None, 1]
           + rays[..., 2] * sun_cam[:, None, None, 2]).clamp_min(0.0)
    source = image * (1.0 - view.alpha) * pow_(cos, _per_image(params.power)[:, 0])[:, None]
    total = radial_blur(source, sun_xy, samples=params.samples, density=params.density, decay=params.decay,
                        weight=params.weight)
    shafts = total * _per_image(params.exposure * facing.clamp_min(0.0))
    return torch.where(_per_image(facing > 1e-6), image + shafts, image)


TONEMAPS = {
    "smoothstep": lambda x, post: smoothstep(_per_image(post.smoothstep_edges[:, 0]), _per_image(post.smoothstep_edges[:, 1]), x),
    "reinhard": lambda x, post: reinhard(x.clamp_min(0.0)),
    "aces": lambda x, post: aces(x.clamp_min(0.0)),
}

POST = Registry("post")
POST.register("fog", Fog, lambda x, post, aovs: distance_fog(x, aovs["distance"], post.fog.color, post.fog.density),
              active=lambda post: post.fog is not None, pass_name=lambda post: "post.fog")
POST.register("god_rays", GodRays, lambda x, post, aovs, view: god_rays(x, post.god_rays, view),
              active=lambda post: post.god_rays is not None, pass_name=lambda post: "post.god_rays", view=True)
POST.register("exposure", float, lambda x, post, aovs: x * _per_image(post.exposure),
              active=lambda post: bool((post.exposure != 1.0).any()), pass_name=lambda post: "post.exposure")
POST.register("tonemap", str, lambda x, post, aovs: TONEMAPS[post.tonemap](x, post),
              active=lambda post: post.tonemap != "none", pass_name=lambda post: f"post.tonemap.{post.tonemap}")
POST.register("vignette", float, lambda x, post, aovs: vignette(x, post.vignette),
              active=lambda post: bool((post.vignette > 0).any()), pass_name=lambda post: "post.vignette")
