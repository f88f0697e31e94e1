"""Directions about a normal or a direction, in lanes (`ops.lanes`): an orthonormal basis, a turn
by an angle and azimuth, the cosine lobe; and the Lambert surface every opaque surface of the path
tracer (`volume.path`: the terrain, the voxels, the planet's ground) reflects and bounces by."""

from __future__ import annotations

import math

from ..ops import lanes

__all__ = ["basis", "facing", "lambert_bounce", "lambert_reflect", "turn"]


def basis(d: list) -> tuple[list, list]:
    """Two unit vectors (three lanes each) completing unit d (three lanes) to an orthonormal basis
    (Duff et al. 2017), lanes."""
    x, y, z = d
    sign = lanes.where(z >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + z)
    b = x * y * a
    return [1.0 + sign * x * x * a, sign * b, -sign * x], [b, sign + y * y * a, -y]


def turn(d: list, cos, u) -> list:
    """The unit direction (three lanes) at angle acos(cos) from d (three lanes), azimuth 2π·u, lanes."""
    t1, t2 = basis(d)
    sin = lanes.sqrt(lanes.clamp_min(1.0 - cos * cos, 0.0))
    phi = 2.0 * math.pi * u
    c, s_ = sin * lanes.cos(phi), sin * lanes.sin(phi)
    return [c * t1[i] + s_ * t2[i] + cos * d[i] for i in range(3)]


def facing(normal: list, direction: list):
    """max(0, n·l) of unit lanes `normal` and `direction` (three lanes each)."""
    return lanes.clamp_min(lanes.dot3(normal, direction), 0.0)


def lambert_reflect(direct: float):
    """A Lambert surface's `reflect(facts, normal, view, light)`: `direct` · max(0, n·l) in every
    colour (the albedo is in the path's throughput already)."""
    return lambda facts, normal, view, light: [direct * facing(normal, light)] * 3


def lambert_bounce(facts, normal: list, d: list, u: list):
    """A Lambert surface's `bounce(facts, normal, d, u)`: cosine-weighted about the normal (u
    uniform lanes), weight 1 in every colour (BRDF·cos/pdf is the albedo, already taken)."""
    return turn(normal, lanes.sqrt(u[0]), u[1]), [1.0] * 3
