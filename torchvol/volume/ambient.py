"""Sky (ambient) light scattered into a medium: σs · L_amb(y) · V, an isotropic term (the sky's
radiance integrated over the sphere against a 1/4π phase gives back its mean radiance).

L_amb is the scene sky's mean radiance over the sphere (its ambient), or an explicit `radiance`,
optionally graded linearly with height to `top` at the top of the volume's bounds (the production
clouds' ambient gradient, seed 000 Step 6 Method C). V, the fraction of that light that reaches the
point, is estimated as production cloud renderers do with one short march: the transmittance
towards the sky along `direction` (up by default: the sky is brightest there and a cloud's base is
the part it cannot reach), with σ_t scaled by `sigma_scale` (< 1: light that reaches the point from
other directions, or diffuses in, is not lost), times the transmittance of the same ray through
every other volume (whatever its shading, its own σ_t unscaled) and the terrain where the scene has
them, as the lights' shadow rays see them (`shadow.occluder_transmittance`, each its own pass
`volume{i}.ambient.volume{j}`, `volume{i}.ambient.terrain`). `visibility = "none"` takes V = 1."""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Literal

import torch
from pydantic import Field, field_validator
from torch import Tensor

from ..geometry.bounds import bounds_lanes
from ..ops import lanes
from ..schema.batch import take
from ..schema.models import Strict, Vec3, nonneg, nonzero
from .context import VolumeContext
from .shadow import line_depth, occluder_transmittance, shadow_transmittance

SKY_DIRECTIONS = 64  # the Fibonacci sphere the sky's mean radiance is averaged over


class Ambient(Strict):
    """`volumes[i].ambient`: sky light in-scattered by the medium, σs · L_amb(y) · V."""

    radiance: Vec3 | None = Field(None, description="None: the [sky]'s mean radiance over the sphere")
    top: Vec3 | None = Field(None, description="radiance at the top of the bounds (radiance at the bottom)")
    visibility: Literal["march", "none"] = "march"
    direction: Vec3 = (0.0, 1.0, 0.0)
    steps: int = Field(4, ge=1, le=256)
    sigma_scale: float = Field(1.0, ge=0.0, le=1.0)
    _r = field_validator("radiance", "top")(lambda v: v if v is None else nonneg(v))

    _d = field_validator("direction")(lambda v: nonzero(v, "towards the sky"))


def fibonacci_sphere(n: int, *, dtype, device) -> Tensor:
    """`n` quasi-uniform unit directions [n, 3]."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    y = 1.0 - 2.0 * i / n
    r = (1.0 - y * y).sqrt()
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return torch.stack([r * phi.cos(), y, r * phi.sin()], dim=1).to(dtype=dtype, device=device)


def sky_mean(sky_fn, sky, sun: Tensor | None, count: int, *, dtype, device) -> Tensor:
    """Each scene's sky radiance averaged over the sphere (B, 3); `sky_fn` the sky kind's function."""
    d = fibonacci_sphere(SKY_DIRECTIONS, dtype=dtype, device=device)
    s = torch.arange(count, device=device).repeat_interleave(SKY_DIRECTIONS)
    return sky_fn(sky, d.repeat(count, 1), s, sun).reshape(count, SKY_DIRECTIONS, 3).mean(dim=1)


def ambient_lanes(vol, per_lane) -> SimpleNamespace:
    """What L_amb takes per lane (`per_lane`: per scene (B, ...) -> lanes): the bottom radiance
    (three lanes) and, where graded, the top's, the bounds' height range (`low`, `high`) and its
    parameters (`bounds.bounds_lanes`) for their ``lanes`` altitude."""
    q = SimpleNamespace(bottom=per_lane(vol.ambient_bottom), top=None)
    if vol.params.ambient.top is not None:
        b = vol.params.bounds.value
        q.top, (q.low, q.high) = per_lane(vol.params.ambient.top), per_lane(vol.bounds.caps["height_range"](b))
        q.bounds, q.altitude = bounds_lanes(b, per_lane), vol.bounds.caps["lanes"][2]
    return q


def ambient_radiance(q: SimpleNamespace, p) -> list:
    """L_amb at `p` (three lanes), in lanes (`ops.lanes`; `q` from `ambient_lanes`): the bottom
    radiance, graded linearly by the altitude (a shell's radial, y otherwise) to `top` at the top
    of the bounds. -> three lanes."""
    if q.top is None:
        return q.bottom
    h = lanes.clamp((q.altitude(q.bounds, p) - q.low) / (q.high - q.low), 0.0, 1.0)
    return [lanes.lerp(q.bottom[c], q.top[c], h) for c in range(3)]


def ambient_in_scatter(ctx: VolumeContext, vol, p: Tensor, s: Tensor, sigma_s: Tensor, density: Tensor) -> Tensor:
    """σs · L_amb · V [n, 3] at points `p` [n, 3] of scenes `s` [n], scattering `sigma_s` [n], the
    field's `density` [n] there (a closed-form visibility starts from it)."""
    amb, use = vol.params.ambient, vol.plan.ambient_sky
    q = ambient_lanes(vol, lambda v: lanes.columns(take(v, s)))
    out = torch.stack(ambient_radiance(q, p.unbind(1)), 1) * sigma_s[:, None]
    if use is None:
        return out
    with ctx.timer.section(use.name):
        direction = take(torch.nn.functional.normalize(amb.direction, dim=1), s)
        exit_t = vol.intersect(p, direction, s)[1].clamp(0.0, vol.plan.reach)
        scale = take(amb.sigma_scale * vol.params.sigma_t, s)
        if vol.plan.line_integral:  # exact: no march
            v = torch.exp(-scale * line_depth(vol, p, s, direction, exit_t, density))
        else:
            v = shadow_transmittance(p, direction, exit_t, lambda q, owner: scale[owner] * vol.field(q, s[owner]),
                                     steps=amb.steps)
        if use.occluders or use.terrain or use.voxels:  # the sky seen through the other volumes, past the surfaces
            v = v * occluder_transmittance(ctx, use, p, s, direction, torch.full_like(v, math.inf))
    return out * v[:, None]


__all__ = ["Ambient", "ambient_in_scatter", "ambient_lanes", "ambient_radiance", "sky_mean"]
