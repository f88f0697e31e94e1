"""Light sources: the `LIGHTS` registry. Each kind is its schema model (a `[[lights]]` table chosen
by its ``kind`` key) and its function `fn(light (Stacked), points [n, 3], scene_index [n]) -> Toward`:
the unit direction towards the light, the irradiance it delivers there (unshadowed) and the
distance to it (where a shadow ray ends; inf for a sun). Capability ``directional``: the same
direction and irradiance everywhere (a sun), so a ray sees one phase angle all along (computed once
per ray), a homogeneous medium has a closed form, and a shadow can be tabulated on a sun grid.
"""

from __future__ import annotations

import math
from typing import Annotated, Callable, Literal, NamedTuple, Sequence

import torch
from pydantic import Field, field_validator
from torch import Tensor

from ..ops import lanes
from ..schema.batch import Stacked, take
from ..schema.models import SHARED, Strict, Vec3, nonneg, nonzero
from ..schema.registry import Registry

# A point light's 1/r² is capped at 1/POINT_RADIUS²: a ray through the light itself stays finite
# (as if the light were a small sphere); it never changes a sample farther than POINT_RADIUS away.
POINT_RADIUS = 1e-4


class Shadow(Strict):
    """How a light's transmittance through the volumes is found: `march` (a shadow march from every
    lit sample to where it leaves the volume, or to the light if that comes first) or `grid` (suns
    only: optical depth tabulated once per scene on `resolution`² × (resolution/2 + 1) sun-aligned
    nodes over each volume's bounds (Simpson's rule along the sun), looked up bicubically across
    the sun plus a trapezoid over the gap to the next plane: far cheaper; box and sphere bounds
    only; hard surfaces of the medium smear over a grid cell). docs/VOLUMES.md has the measured
    error and time of both. A volume whose optical depth along a line has a closed form (a
    constant or an exponential height profile, without an edge fade) takes it instead, whichever the method:
    exact, from the density where the ray starts, no grid (`stats["plan"]["closed_form_shadows"]`).
    Shadow settings are accuracy settings, shared by a batch."""

    method: Literal["march", "grid"] = "march"
    steps: int | None = Field(None, ge=1, le=4096, description="None: the quality level's")
    growth: Annotated[float, SHARED] = Field(1.0, ge=1.0, le=4.0)
    first_step: Annotated[float | None, SHARED] = Field(None, gt=0.0)
    resolution: int = Field(128, ge=4, le=1024)


def _color(v: Vec3) -> Vec3:
    return nonneg(v)


class Sun(Strict):
    """A directional light: irradiance `intensity · color` from `direction` (towards the sun)."""

    kind: Literal["sun"] = "sun"
    direction: Vec3 = (1.0, 1.0, -0.5)
    color: Vec3 = (1.0, 1.0, 1.0)
    intensity: float = Field(1.0, ge=0.0)
    shadow: Shadow | None = None

    _d = field_validator("direction")(lambda v: nonzero(v, "it points towards the sun"))

    _c = field_validator("color")(lambda v: _color(v))


class Point(Strict):
    """A point light of radiant intensity `intensity · color` at `position`: irradiance
    `intensity · color / r²` at distance r (r² capped below at POINT_RADIUS²)."""

    kind: Literal["point"] = "point"
    position: Vec3 = (0.0, 2.0, 0.0)
    color: Vec3 = (1.0, 1.0, 1.0)
    intensity: float = Field(1.0, ge=0.0)
    shadow: Shadow | None = None

    _c = field_validator("color")(lambda v: _color(v))


class Toward(NamedTuple):
    direction: Tensor  # [n, 3] unit, towards the light
    irradiance: Tensor  # [n, 3] unshadowed
    distance: Tensor  # [n] to the light (inf: a sun)


def radiant(light: Stacked) -> Tensor:
    """intensity · color (B, 3): a sun's irradiance, a point light's radiant intensity."""
    return light.color * light.intensity[:, None]


def sun_direction(light: Stacked) -> Tensor:
    """(B, 3) unit, towards the sun."""
    return torch.nn.functional.normalize(light.direction, dim=-1)


def sun_toward(light: Stacked, points: Tensor, s: Tensor) -> Toward:
    """A sun as seen from `points` [n, 3] of scenes `s` [n]: its unit direction [n, 3], its
    irradiance [n, 3] and an infinite distance [n]."""
    n = points.shape[0]
    return Toward(take(sun_direction(light), s), take(radiant(light), s), points.new_full((n,), math.inf))


def point_toward(light: Stacked, points: Tensor, s: Tensor) -> Toward:
    """A point light as seen from `points` [n, 3] of scenes `s` [n]: the unit direction to it
    [n, 3], its irradiance there [n, 3] (falling off as 1/r², r no less than POINT_RADIUS) and
    the distance [n]."""
    direction, irradiance, r = point_lanes(take(light.position, s).unbind(1), take(radiant(light), s).unbind(1),
                                           points.unbind(1))
    return Toward(torch.stack(direction, 1), torch.stack(irradiance, 1), r)


def point_lanes(position, radiant_intensity, p):
    """A point light at `position` of `radiant_intensity` (three lanes each) seen from `p` (three
    lanes), in lanes (`ops.lanes`): (unit direction to it, irradiance there (1/r², r no less than
    POINT_RADIUS), each three lanes; the distance r)."""
    v = [position[c] - p[c] for c in range(3)]
    r2 = lanes.clamp_min(v[0] * v[0] + v[1] * v[1] + v[2] * v[2], POINT_RADIUS * POINT_RADIUS)
    r = lanes.sqrt(r2)
    return [c / r for c in v], [e / r2 for e in radiant_intensity], r


LIGHTS = Registry("light")
LIGHTS.register("sun", Sun, sun_toward, directional=True)
LIGHTS.register("point", Point, point_toward, directional=False)


def sun_index(lights: Sequence) -> int | None:
    """The index of the scene's sun among `lights` (a scene's or a batch's `[[lights]]`, each with
    a `kind`): lights[0] where it is directional, as in the seeds, else None. Skies, their halo and
    flare, the atmosphere, god rays and the ``sun_visibility`` label are lit by it; the rule is
    written here once and the plan records its answer (`Plan.sun`)."""
    return 0 if lights and LIGHTS[lights[0].kind].caps["directional"] else None


class LightSource:
    """One light index across a batch: its kind and its `Stacked` parameters, and `through`: what
    lies between it and any point of the scene that is not part of the scene (the `[atmosphere]`'s
    air on the sun's way), `through(points [n, 3], s [n]) -> transmittance [n, 3]`, or None."""

    def __init__(self, kind, params: Stacked):
        self.kind, self.params = kind, params
        self.directional: bool = kind.caps["directional"]
        self.radiant = radiant(params)  # (B, 3)
        self.direction = sun_direction(params) if self.directional else None  # (B, 3)
        self.through: Callable[[Tensor, Tensor], Tensor] | None = None

    def toward(self, points: Tensor, s: Tensor) -> Toward:
        """Direction, irradiance and distance to the light from `points` [n, 3] of scenes `s` [n]
        (the irradiance as it arrives: through the air where there is one)."""
        toward = self.kind.fn(self.params, points, s)
        if self.through is None:
            return toward
        return toward._replace(irradiance=toward.irradiance * self.through(points, s))

    def leaving(self, points: Tensor, s: Tensor) -> Toward:
        """`toward` before `through`: the light as it leaves its source (a march that takes a sun's
        irradiance once per ray applies `through` at each sample)."""
        return self.kind.fn(self.params, points, s)
