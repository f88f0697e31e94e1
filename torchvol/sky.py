"""Sky radiance along view directions: constant, the seeds' gradient, and the sun's glow lobes."""

from __future__ import annotations

from torch import Tensor


def gradient_sky(directions: Tensor, horizon: Tensor, slope: Tensor) -> Tensor:
    """The template's `bgcol = horizon − rd.y · slope`. `directions`: [R, 3]; `horizon`, `slope`:
    [R, 3] (gathered per ray). -> [R, 3]."""
    return horizon - directions[:, 1:2] * slope


def sun_glow(directions: Tensor, sun_dir: Tensor, color: Tensor, power: Tensor) -> Tensor:
    """color · clamp(dot(sun, rd), 0, 1)^power: the template's halo (power 8) and flare (power 3).
    `directions`, `sun_dir`, `color`: [R, 3]; `power`: [R]. -> [R, 3]."""
    sun = (directions * sun_dir).sum(dim=1).clamp(0.0, 1.0)
    return color * sun.pow(power)[:, None]
