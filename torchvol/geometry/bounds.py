"""Where a volume's medium lives: box, sphere, horizontal slab or a planet's shell. Each kind gives its entry/exit
distances along rays (`intersect`), the box around it (`aabb`, finite kinds only: the sun grid
tabulates over it), its height range (`height_range`: the shader look's height gradient, the ambient
gradient) and the distance in to its surface (`depth`: the edge fade); its interval, depth and
altitude (y, or a shell's radial height) written once in lanes (`lanes`: what the Dr.Jit march
traces, and what the eager functions run on torch columns)."""

from __future__ import annotations

from types import SimpleNamespace

import torch
from pydantic import Field, model_validator
from torch import Tensor

from ..ops import lanes
from ..runtime.compilation import traced
from ..schema.batch import Stacked, take
from ..schema.models import Strict, Vec3
from ..schema.registry import Registry
from .rays import (
    box_interval,
    intersect_box,
    intersect_shell,
    intersect_slab,
    intersect_sphere,
    shell_interval,
    slab_interval,
    sphere_interval,
)

SLAB_REACH = 1e5  # world units a ray may travel in a slab unless march.max_distance says otherwise


class Box(Strict):
    min: Vec3 = (-0.5, -0.5, -0.5)
    max: Vec3 = (0.5, 0.5, 0.5)

    @model_validator(mode="after")
    def _ordered(self):
        if any(hi <= lo for lo, hi in zip(self.min, self.max)):
            raise ValueError(f"max {self.max} must exceed min {self.min} on every axis")
        return self


class Sphere(Strict):
    center: Vec3 = (0.0, 0.0, 0.0)
    radius: float = Field(1.0, gt=0.0)


class Slab(Strict):
    y_min: float = -1.0
    y_max: float = 1.0

    @model_validator(mode="after")
    def _ordered(self):
        if self.y_max <= self.y_min:
            raise ValueError(f"y_max {self.y_max} must exceed y_min {self.y_min}")
        return self


class Shell(Strict):
    """A layer between altitudes `bottom` and `top` over an opaque planet of `planet_radius`
    centred at (0, −planet_radius, 0), so that its ground passes through the origin."""

    planet_radius: float = Field(6000.0, gt=0.0)
    bottom: float = Field(1.5, ge=0.0)
    top: float = 4.0

    @model_validator(mode="after")
    def _ordered(self):
        if self.top <= self.bottom:
            raise ValueError(f"top {self.top} must exceed bottom {self.bottom}")
        return self


# Every function takes the bounds of B scenes (`Stacked`): `intersect(b, o [n, 3], d [n, 3], s [n])
# -> (t_near [n], t_far [n])`; `aabb(b) -> (min (B, 3), max (B, 3))`; `height_range(b) -> (B, 2)`;
# `lowest_y(b) -> (B,)`: the least world y inside (a slab's too, which has no box);
# `depth(b, p [n, 3], s [n]) -> [n]`: distance from p in to the surface (negative outside; `edge`).

def _box_intersect(b: Stacked, o: Tensor, d: Tensor, s: Tensor) -> tuple[Tensor, Tensor]:
    return intersect_box(o, d, take(b.min, s), take(b.max, s))


def _sphere_intersect(b: Stacked, o: Tensor, d: Tensor, s: Tensor) -> tuple[Tensor, Tensor]:
    return intersect_sphere(o, d, take(b.center, s), take(b.radius, s))


def _slab_intersect(b: Stacked, o: Tensor, d: Tensor, s: Tensor) -> tuple[Tensor, Tensor]:
    return intersect_slab(o, d, take(b.y_min, s), take(b.y_max, s))


def _shell_center(b: Stacked) -> Tensor:
    """(B, 3): the planet's centre, below the origin."""
    zero = torch.zeros_like(b.planet_radius)
    return torch.stack([zero, -b.planet_radius, zero], dim=1)


def _shell_intersect(b: Stacked, o: Tensor, d: Tensor, s: Tensor) -> tuple[Tensor, Tensor]:
    r = take(b.planet_radius, s)
    return intersect_shell(o, d, take(_shell_center(b), s), r, r + take(b.bottom, s), r + take(b.top, s))


def _shell_aabb(b: Stacked) -> tuple[Tensor, Tensor]:
    reach = (b.planet_radius + b.top)[:, None]
    return _shell_center(b) - reach, _shell_center(b) + reach


def box_depth(p, lo, hi):
    """The distance from `p` in to the box's nearest face, lanes (`ops.lanes`): p, lo, hi three
    lanes each."""
    m = [lanes.minimum(p[i] - lo[i], hi[i] - p[i]) for i in range(3)]
    return lanes.minimum(lanes.minimum(m[0], m[1]), m[2])


def sphere_depth(p, center, radius):
    """The distance from `p` in to the sphere's surface, lanes: p, center three lanes each."""
    return radius - lanes.length3(p[0] - center[0], p[1] - center[1], p[2] - center[2])


def _box_depth(b: Stacked, p: Tensor, s: Tensor) -> Tensor:
    return box_depth(p.unbind(1), take(b.min, s).unbind(1), take(b.max, s).unbind(1))


def _sphere_depth(b: Stacked, p: Tensor, s: Tensor) -> Tensor:
    return sphere_depth(p.unbind(1), take(b.center, s).unbind(1), take(b.radius, s))


def slab_depth(p, y_min, y_max):
    """The distance from `p` in to the layer's nearer plane, lanes: p three lanes."""
    return lanes.minimum(p[1] - y_min, y_max - p[1])


def _slab_depth(b: Stacked, p: Tensor, s: Tensor) -> Tensor:
    return slab_depth(p.unbind(1), take(b.y_min, s), take(b.y_max, s))


def shell_altitude(p, radius):
    """Altitude of `p` (three lanes) above the planet of `radius` centred at (0, −radius, 0), in
    lanes: |p − centre| − radius written as (x² + z² + y·(y + 2·radius)) / (|p − centre| +
    radius), which does not cancel (a layer a few units above a planet of 1000: in float32 the
    difference of two lengths near 1000 was off by up to 9e-5, this form by 1.5e-6)."""
    x, y, z = p
    return (x * x + z * z + y * (y + 2.0 * radius)) / (lanes.length3(x, y + radius, z) + radius)


def shell_depth(p, radius, bottom, top):
    """The distance from `p` in to the shell's nearer sphere (its altitude's), lanes: p three lanes."""
    altitude = shell_altitude(p, radius)
    return lanes.minimum(altitude - bottom, top - altitude)


def shell_lanes_interval(q: SimpleNamespace, o, d):
    """The shell's (t_near, t_far) along lanes o, d over its parameters per lane `q` (`bounds_lanes`)."""
    r = q.planet_radius
    return shell_interval(o, d, (0.0, -r, 0.0), r, r + q.bottom, r + q.top)


def _shell_depth(b: Stacked, p: Tensor, s: Tensor) -> Tensor:
    return shell_depth(p.unbind(1), take(b.planet_radius, s), take(b.bottom, s), take(b.top, s))


def bounds_lanes(b: Stacked, per_lane) -> SimpleNamespace:
    """The bounds' parameters per lane (`per_lane`: per scene (B, ...) -> lanes; a vector three
    lanes), what their ``lanes`` functions take."""
    return SimpleNamespace(**{name: per_lane(getattr(b, name)) for name in type(b.models[0]).model_fields})


def intersect_kernel(kind, b: Stacked, o: Tensor, d: Tensor, s: Tensor) -> tuple[Tensor, Tensor]:
    """`kind.fn(b, o, d, s)` (t_near, t_far) [n] of rays o, d [n, 3] (float32, CPU) of scenes s [n]
    as one Dr.Jit kernel: the kind's lanes interval over each ray's parameters gathered by scene in
    the kernel (a shell's eager interval was ~60 torch passes over the rays: 4.5 ms of a 256²
    cloudscape). Its sqrt is Dr.Jit's (correctly rounded, torch's float32 one is not): a sphere's
    and a shell's ends within a few ulps of eager's (4 in tests/test_rays.py), a box's and a slab's
    bitwise."""
    per_lane = lanes.per_scene_lanes(s)
    near, far = traced(lambda lane: kind.lanes[0](bounds_lanes(b, per_lane), lanes.vector_lanes(o), lanes.vector_lanes(d)), o)
    return near, far


def _sphere_aabb(b: Stacked) -> tuple[Tensor, Tensor]:
    return b.center - b.radius[:, None], b.center + b.radius[:, None]


def _heights(lo: Tensor, hi: Tensor) -> Tensor:
    return torch.stack([lo, hi], dim=1)


BOUNDS = Registry("bounds")
# `lanes`: the kind's (interval, depth, altitude) in lanes over its parameters per lane `q`
# (`bounds_lanes`): interval(q, o, d) -> (t_near, t_far), depth(q, p) -> distance in, altitude(q, p)
# -> the height its `height_range` grades (y, or a shell's radial altitude); what a kernel traces.
# `traced_interval`: a kernel march takes the camera rays' interval from a Dr.Jit kernel too
# (`intersect_kernel`; 65 k rays, two threads: a shell's 3.8 -> 0.7 ms, a sphere's 1.7 -> 0.6, a
# box's 1.1 -> 0.8; a slab's two divisions stay eager, 0.4 ms against the kernel's 0.5)
_height = lambda q, p: p[1]  # noqa: E731
BOUNDS.register("box", Box, _box_intersect, finite=True, layer=False, aabb=lambda b: (b.min, b.max), traced_interval=True,
                lowest_y=lambda b: b.min[:, 1],
                height_range=lambda b: _heights(b.min[:, 1], b.max[:, 1]), depth=_box_depth,
                lanes=(lambda q, o, d: box_interval(o, d, q.min, q.max), lambda q, p: box_depth(p, q.min, q.max), _height))
BOUNDS.register("sphere", Sphere, _sphere_intersect, finite=True, layer=False, aabb=_sphere_aabb, traced_interval=True,
                lowest_y=lambda b: b.center[:, 1] - b.radius,
                height_range=lambda b: _heights(b.center[:, 1] - b.radius, b.center[:, 1] + b.radius), depth=_sphere_depth,
                lanes=(lambda q, o, d: sphere_interval(o, d, q.center, q.radius),
                       lambda q, p: sphere_depth(p, q.center, q.radius), _height))
# `layer`: a layer over the ground (a slab, a planet's shell), far wider than what a view of it marches
# a slab's exit is at infinity along its planes: rays stop at SLAB_REACH unless march.max_distance says
BOUNDS.register("slab", Slab, _slab_intersect, finite=False, layer=True, aabb=None, traced_interval=False,
                lowest_y=lambda b: b.y_min,
                height_range=lambda b: _heights(b.y_min, b.y_max),
                depth=_slab_depth, lanes=(lambda q, o, d: slab_interval(o, d, q.y_min, q.y_max),
                                          lambda q, p: slab_depth(p, q.y_min, q.y_max), _height))
BOUNDS.register("shell", Shell, _shell_intersect, finite=True, layer=True, aabb=_shell_aabb, traced_interval=True,
                lowest_y=lambda b: _shell_aabb(b)[0][:, 1],
                height_range=lambda b: _heights(b.bottom, b.top), depth=_shell_depth,
                lanes=(shell_lanes_interval, lambda q, p: shell_depth(p, q.planet_radius, q.bottom, q.top),
                       lambda q, p: shell_altitude(p, q.planet_radius)))
