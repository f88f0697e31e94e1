"""Volumes lit as surfaces (`shading = "surface"`, the seeds' variant 5, the fur ball): each sample's
normal is N = −normalize(∇density) by finite differences, lit by half-Lambert diffuse
max(0, N·L·0.5 + 0.5) plus Blinn-Phong specular max(0, N·H)^shininess from every light
(unshadowed), and composited front to back as the seeds' alpha (alpha = density · alpha_scale)."""

from __future__ import annotations

from typing import Literal

import torch
from pydantic import Field
from torch import Tensor

from ..geometry.camera import Rays
from ..ops.mathops import pow_
from ..schema.batch import take
from ..schema.models import Strict, Vec3
from .context import VolumeContext
from .march import Medium
from .shader_look import alpha_look_medium


class SurfaceLook(Strict):
    """colour = ambient + Σ lights E · (diffuse · half-Lambert + specular · Blinn-Phong), alpha =
    density · alpha_scale. `gradient`: "central" differences (6 density samples per lit sample) or
    the seed's furNormal, "forward" differences from the sample's own density (3)."""

    diffuse: Vec3 = (0.8, 0.55, 0.35)
    specular: Vec3 = (0.4, 0.4, 0.4)
    shininess: float = Field(50.0, gt=0.0, le=1e4)
    ambient: Vec3 = (0.0, 0.0, 0.0)
    epsilon: float = Field(0.01, gt=0.0, le=1.0)
    gradient: Literal["central", "forward"] = "central"
    alpha_scale: float = Field(0.4, ge=0.0)


_AXES = torch.eye(3, dtype=torch.float64)


def density_normal(field, p: Tensor, s: Tensor, density: Tensor, epsilon: Tensor, *,
                   gradient: Literal["central", "forward"], lod: Tensor | None = None) -> Tensor:
    """N = −normalize(finite-difference gradient of `field`) at points `p` [n, 3] of scenes `s` [n]
    with their densities `density` [n], step `epsilon` [n] -> [n, 3] (the zero vector where the
    density is flat, where GLSL's normalize is undefined)."""
    n = p.shape[0]
    steps = epsilon[None, :, None] * _AXES.to(p)[:, None, :]  # [3, n, 3]
    signs = (1.0, -1.0) if gradient == "central" else (1.0,)
    points = torch.cat([(p + sign * steps).reshape(3 * n, 3) for sign in signs])
    reps = 3 * len(signs)
    values = field(points, s.repeat(reps), None if lod is None else lod.repeat(reps)).view(len(signs), 3, n)
    grad = (values[0] - values[1] if gradient == "central" else values[0] - density).T
    return -grad / torch.sqrt(_dot(grad, grad)).clamp_min(1e-30)[:, None]


def surface_light(normal: Tensor, to_light: Tensor, to_eye: Tensor, shininess: Tensor) -> tuple[Tensor, Tensor]:
    """Half-Lambert diffuse max(0, N·L·0.5 + 0.5) and Blinn-Phong specular max(0, N·H)^shininess,
    H = normalize(L + V). `normal`, `to_light`, `to_eye`: [n, 3] (unit); `shininess`: [n] (> 0).
    -> (diffuse [n], specular [n])."""
    half = to_light + to_eye
    n_dot_h = _dot(normal, half) / torch.sqrt(_dot(half, half)).clamp_min(1e-30)
    diffuse = (_dot(normal, to_light) * 0.5 + 0.5).clamp_min(0.0)
    specular = pow_(n_dot_h.clamp_min(0.0), shininess)
    return diffuse, specular


def _dot(a: Tensor, b: Tensor) -> Tensor:
    """Row dot products of `a`, `b` [n, 3] -> [n], elementwise (a reduction's rounding could
    depend on n or strides; batches must match single renders to the bit)."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def surface_medium(ctx: VolumeContext, vol, rays: Rays, background: Tensor | None, *, signed: bool = False) -> Medium:
    """(alpha [n], colour [n, 3]) of the surface look at each sample (`background` and `signed`
    do not apply)."""
    look = vol.params.surface

    def shade(ids, keep, s, p, t, d, density, lod):
        normal = density_normal(vol.field, p, s, density, take(look.epsilon, s), gradient=look.gradient, lod=lod)
        to_eye, shininess = -d, take(look.shininess, s)
        diffuse, specular = take(look.diffuse, s), take(look.specular, s)
        col = take(look.ambient, s)
        for use in vol.plan.lights:
            toward = ctx.lights[use.light].toward(p, s)
            dif, spec = surface_light(normal, toward.direction, to_eye, shininess)
            col = col + toward.irradiance * (diffuse * dif[:, None] + specular * spec[:, None])
        return (density * take(look.alpha_scale, s)).clamp_max(1.0), col

    return alpha_look_medium(ctx, vol, rays, shade)
