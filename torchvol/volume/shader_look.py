"""The seeds' non-physical look (`shading = "shader"`): alpha = density · alpha_scale, colour =
mix(color_lit, color_dark, density) · (light colour · derivative light + ambient), fogged towards
the sky by 1 − exp(−fog · t²); composited as the seeds' alpha (clamped sums)."""

from __future__ import annotations

from collections.abc import Callable
from types import SimpleNamespace
from typing import Literal

import torch
from pydantic import Field
from torch import Tensor

from ..geometry.camera import Rays
from ..ops import lanes
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


def derivative_light(density, density_towards_light, *, scale):
    """The seeds' directional-derivative light: clamp((d − d(p + o·L)) / scale, 0, 1); lanes
    (`ops.lanes`), or [N] tensors."""
    return lanes.clamp((density - density_towards_light) / scale, 0.0, 1.0)


def look_lanes(vol, to) -> SimpleNamespace:
    """The look's parameters per lane (`to.per_lane`: per scene -> a lane, or three)."""
    look = vol.params.shader
    q = SimpleNamespace(**{k: to.per_lane(getattr(look, k)) for k in (
        "ambient", "color_lit", "color_dark", "alpha_scale", "fog", "light_offset", "light_scale")})
    q.top = None if look.ambient_top is None else to.per_lane(look.ambient_top)
    if q.top is not None:
        heights = vol.bounds.height_range(vol.params.bounds.value)  # (B, 2)
        q.low, q.high = to.per_lane(heights[:, 0]), to.per_lane(heights[:, 1])
    return q


def ambient_light(q: SimpleNamespace, y) -> list:
    """The look's ambient light at height `y` (a lane; `q` from `look_lanes`): three lanes."""
    if q.top is None:
        return list(q.ambient)
    h = lanes.clamp((y - q.low) / (q.high - q.low), 0.0, 1.0)
    return [lanes.lerp(q.ambient[c], q.top[c], h) for c in range(3)]


def shaded(q: SimpleNamespace, density, light: list, behind: list, t) -> tuple:
    """(alpha, colour: three lanes) of a sample of `density` at distance `t` lit by `light` (three
    lanes), fogged towards `behind` (the sky there, three lanes); `q` from `look_lanes`."""
    col = [lanes.lerp(q.color_lit[c], q.color_dark[c], density) * light[c] for c in range(3)]
    fog = 1.0 - lanes.exp(-q.fog * t * t)
    return density * q.alpha_scale, [lanes.lerp(col[c], behind[c], fog) for c in range(3)]


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
    """(alpha [n], colour [n, 3]) of the look at each sample (`signed` does not apply): its lanes
    functions (`ambient_light`, `derivative_light`, `shaded`) on torch columns."""

    def shade(ids, keep, s, p, t, d, density, lod):
        q = look_lanes(vol, SimpleNamespace(per_lane=lambda v: lanes.columns(take(v, s))))
        lin = ambient_light(q, p[:, 1])
        for use in vol.plan.lights:  # the derivative light: the first light only
            with ctx.timer.section(use.name):
                toward = ctx.lights[use.light].toward(p, s)
                ahead = vol.field(p + q.light_offset[:, None] * toward.direction, s, lod)
                dif = derivative_light(density, ahead, scale=q.light_scale)
                lin = [toward.irradiance[:, c] * dif + lin[c] for c in range(3)]
        behind = background[ids][keep] if background is not None else p.new_zeros(p.shape[0], 3)  # no [sky]: black
        alpha, col = shaded(q, density, lin, behind.unbind(1), t)
        return alpha, torch.stack(col, 1)

    return alpha_look_medium(ctx, vol, rays, shade)

