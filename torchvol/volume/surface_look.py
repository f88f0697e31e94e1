"""Volumes lit as surfaces (`shading = "surface"`, the seeds' variant 5, the fur ball): each sample's
normal is N = −normalize(∇density) by finite differences, lit by half-Lambert diffuse
max(0, N·L·0.5 + 0.5) plus Blinn-Phong specular max(0, N·H)^shininess from every light
(unshadowed), and composited front to back as the seeds' alpha (alpha = density · alpha_scale)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Literal

import torch
from pydantic import Field
from torch import Tensor

from ..geometry.camera import Rays
from ..ops import lanes
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


def density_normal(field, p: Tensor, s: Tensor, density: Tensor, epsilon: Tensor, *,
                   gradient: Literal["central", "forward"], lod: Tensor | None = None) -> Tensor:
    """N = −normalize(finite-difference gradient of `field`) at points `p` [n, 3] of scenes `s` [n]
    with their densities `density` [n], step `epsilon` [n] -> [n, 3] (the zero vector where the
    density is flat, where GLSL's normalize is undefined): `look_normal` on torch columns."""
    density_at = lambda q: field(torch.stack(q, 1), s, lod)  # noqa: E731
    return torch.stack(look_normal(density_at, p.unbind(1), density, epsilon, gradient=gradient), 1)


def look_normal(density_at, p, density, epsilon, *, gradient: Literal["central", "forward"]) -> list:
    """−normalize(finite-difference gradient) at p (three lanes) of density `density`, step
    `epsilon`, `density_at(three lanes)` the field: three lanes (`ops.lanes`)."""
    grad = []
    for a in range(3):
        ahead = density_at([p[c] + epsilon if c == a else p[c] for c in range(3)])
        grad.append(ahead - (density_at([p[c] - epsilon if c == a else p[c] for c in range(3)])
                             if gradient == "central" else density))
    norm = lanes.clamp_min(lanes.sqrt(lanes.dot3(grad, grad)), 1e-30)
    return [-g / norm for g in grad]


def surface_light(normal, to_light, to_eye, shininess) -> tuple:
    """Half-Lambert diffuse max(0, N·L·0.5 + 0.5) and Blinn-Phong specular max(0, N·H)^shininess,
    H = normalize(L + V), lanes: `normal`, `to_light`, `to_eye` three lanes each (unit),
    `shininess` (> 0). -> (diffuse, specular)."""
    half = [to_light[c] + to_eye[c] for c in range(3)]
    n_dot_h = lanes.dot3(normal, half) / lanes.clamp_min(lanes.sqrt(lanes.dot3(half, half)), 1e-30)
    diffuse = lanes.clamp_min(lanes.dot3(normal, to_light) * 0.5 + 0.5, 0.0)
    specular = pow_(lanes.clamp_min(n_dot_h, 0.0), shininess)
    return diffuse, specular


def surface_colour(q: SimpleNamespace, normal, to_eye, lights) -> list:
    """ambient + Σ lights E · (diffuse · half-Lambert + specular · Blinn-Phong): three lanes;
    `lights` (direction, irradiance) pairs of three lanes each, `q` from `surface_lanes`."""
    col = list(q.ambient)
    for direction, irradiance in lights:
        dif, spec = surface_light(normal, direction, to_eye, q.shininess)
        col = [col[c] + irradiance[c] * (q.diffuse[c] * dif + q.specular[c] * spec) for c in range(3)]
    return col


def surface_lanes(vol, to) -> SimpleNamespace:
    """The look's parameters per lane (`to.per_lane`: per scene -> a lane, or three)."""
    look = vol.params.surface
    return SimpleNamespace(**{k: to.per_lane(getattr(look, k)) for k in (
        "diffuse", "specular", "shininess", "ambient", "epsilon", "alpha_scale")}, gradient=look.gradient)


def surface_medium(ctx: VolumeContext, vol, rays: Rays, background: Tensor | None, *, signed: bool = False) -> Medium:
    """(alpha [n], colour [n, 3]) of the surface look at each sample (`background` and `signed`
    do not apply)."""

    def shade(ids, keep, s, p, t, d, density, lod):
        q = surface_lanes(vol, SimpleNamespace(per_lane=lambda v: lanes.columns(take(v, s))))
        normal = density_normal(vol.field, p, s, density, q.epsilon, gradient=q.gradient, lod=lod)
        lights = [(x.direction.unbind(1), x.irradiance.unbind(1))
                  for x in (ctx.lights[use.light].toward(p, s) for use in vol.plan.lights)]
        col = surface_colour(q, normal.unbind(1), (-d).unbind(1), lights)
        return lanes.clamp_max(density * q.alpha_scale, 1.0), torch.stack(col, 1)

    return alpha_look_medium(ctx, vol, rays, shade)
