"""The seeds' non-physical look (`shading = "shader"`): alpha = density · alpha_scale, colour =
mix(color_lit, color_dark, density) · (light colour · derivative light + ambient), fogged towards
the sky by 1 − exp(−fog · t²); composited as the seeds' alpha (clamped sums)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import torch
from pydantic import Field
from torch import Tensor

from ..geometry.camera import Rays
from ..schema.batch import take
from ..schema.models import Strict, Vec3
from .context import VolumeContext
from .march import Medium, gathered, lod_drop


class ShaderLook(Strict):
    """The seeds' non-physical look (shading = "shader"): alpha = density·alpha_scale, colour =
    mix(color_lit, color_dark, density) · (light colour · derivative light + ambient), fog towards
    the sky. The derivative light is the first light's (none without lights)."""

    light: Literal["derivative", "none"] = "derivative"
    light_offset: float = Field(0.3, gt=0.0)
    light_scale: float = Field(0.6, gt=0.0)
    ambient: Vec3 = (0.91, 0.98, 1.05)
    # height gradient (seed Step 6 Method C): ambient = mix(ambient, ambient_top, normalised height
    # in the bounds); e.g. ambient = [0.229, 0.394, 0.512], ambient_top = [0.876, 0.982, 1.176]
    ambient_top: Vec3 | None = None
    color_lit: Vec3 = (1.0, 0.95, 0.8)
    color_dark: Vec3 = (0.25, 0.3, 0.35)
    alpha_scale: float = Field(0.4, ge=0.0)
    fog: float = Field(0.0, ge=0.0)  # mix towards the sky by 1 − exp(−fog·t²)


def derivative_light(density: Tensor, density_towards_light: Tensor, *, scale: Tensor | float) -> Tensor:
    """The seeds' directional-derivative light: clamp((d − d(p + o·L)) / scale, 0, 1).

    `density`, `density_towards_light`: [N]; `scale`: [N] or scalar. -> [N]."""
    return ((density - density_towards_light) / scale).clamp(0.0, 1.0)


def ambient(vol, p: Tensor, s: Tensor) -> Tensor:
    """The look's ambient light at points `p` [n, 3] of scenes `s` [n] -> [n, 3]."""
    look = vol.params.shader
    if look.ambient_top is None:
        return take(look.ambient, s)
    heights = take(vol.bounds.height_range(vol.params.bounds.value), s)  # [n, 2]
    height = ((p[:, 1] - heights[:, 0]) / (heights[:, 1] - heights[:, 0])).clamp(0.0, 1.0)
    return torch.lerp(take(look.ambient, s), take(look.ambient_top, s), height[:, None])


def alpha_look_medium(ctx: VolumeContext, vol, rays: Rays, shade: Callable[..., tuple[Tensor, Tensor]]) -> Medium:
    """The medium of an alpha look (the seeds' loop): the density at each sample, and where it is
    over `march.density_threshold`, `shade(ids, keep, s, p, t, d, density, lod)` of those samples
    (`ids` the march's rays, `keep` [k] the samples shaded, the rest [k]/[k, 3]) -> (alpha [k],
    colour [k, 3]); elsewhere alpha 0."""
    o, d_all, s_all = rays.origins, rays.directions, rays.scene_index
    threshold, lod_scale = ctx.settings.density_threshold, ctx.settings.lod_scale
    at = gathered(lambda ids: (s_all[ids], o[ids], d_all[ids]))

    def medium(ids: Tensor, t: Tensor, dt: Tensor):
        s, o_ids, d_ids = at(ids)
        p = torch.addcmul(o_ids, t[:, None], d_ids)
        lod = lod_drop(t, lod_scale)
        density = vol.field(p, s, lod)
        alpha = torch.zeros_like(density)
        color = p.new_zeros(p.shape[0], 3)
        keep = (density > threshold).nonzero().squeeze(1)
        if keep.numel():
            alpha[keep], color[keep] = shade(ids, keep, s[keep], p[keep], t[keep], d_ids[keep], density[keep],
                                             None if lod is None else lod[keep])
        return alpha, color

    return medium


def shader_medium(ctx: VolumeContext, vol, rays: Rays, background: Tensor | None, *, signed: bool = False) -> Medium:
    """(alpha [n], colour [n, 3]) of the look at each sample (`signed` does not apply)."""
    look = vol.params.shader

    def shade(ids, keep, s, p, t, d, density, lod):
        lin = ambient(vol, p, s)
        for use in vol.plan.lights:  # the derivative light: the first light only
            with ctx.timer.section(use.name):
                toward = ctx.lights[use.light].toward(p, s)
                ahead = vol.field(p + take(look.light_offset, s)[:, None] * toward.direction, s, lod)
                dif = derivative_light(density, ahead, scale=take(look.light_scale, s))
                lin = toward.irradiance * dif[:, None] + lin
        col = torch.lerp(take(look.color_lit, s), take(look.color_dark, s), density[:, None]) * lin
        fog = take(look.fog, s)
        behind = background[ids][keep] if background is not None else torch.zeros_like(col)  # no [sky]: black
        col = torch.lerp(col, behind, (1.0 - torch.exp(-fog * t * t))[:, None])
        return density * take(look.alpha_scale, s), col

    return alpha_look_medium(ctx, vol, rays, shade)
