"""Ray / bounds intersection: pure tensor functions, never NaN.

All functions take ``origins [R, 3]`` and ``directions [R, 3]`` (unit) and return
``(t_near [R], t_far [R])`` along the infinite line ``o + t d``.

Contract:

* ``t_near > t_far`` means a miss. Every miss is returned canonically as ``(+inf, -inf)``.
* A hit has ``t_near <= t_far`` (``==`` for a tangent/edge touch, a zero-length hit); the
  interval may start behind the origin (``t_near < 0 < t_far``: origin inside) — the caller clips
  with :func:`clip_to_ray`.
* Bounds are closed sets: a point on the boundary is inside. A ray parallel to a slab (a zero
  direction component, ``+0.0`` or ``-0.0``) has the unbounded interval ``(-inf, +inf)`` for that
  slab when its origin lies inside it (boundary included) and misses otherwise; the ``0 * inf``
  NaN trap is avoided with ``torch.where``, never by nudging the direction.
* Never NaN for finite inputs, including origins exactly on faces, edges and corners, grazing rays
  and rays whose slab distances overflow.

Parameters broadcast: ``box_min``/``box_max``/``center`` are ``[3]`` or ``[R, 3]``; ``radius``,
``y_min``, ``y_max`` are scalars or ``[R]``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..ops import lanes

__all__ = ["intersect_box", "intersect_sphere", "intersect_slab", "clip_to_ray"]


def _as(x, like: Tensor) -> Tensor:
    return torch.as_tensor(x, dtype=like.dtype, device=like.device)


def _canonical(t_near, t_far, miss):
    """Set misses (and empty/infinite-degenerate intervals) to (+inf, -inf). Lanes (`ops.lanes`)."""
    miss = miss | ~(t_near <= t_far) | (t_near == float("inf")) | (t_far == float("-inf"))
    return lanes.where(miss, float("inf"), t_near), lanes.where(miss, float("-inf"), t_far)


def _slab(o, d, lo, hi):
    """Per-component slab interval: (t_lo, t_hi, miss) elementwise, NaN-free; lanes (`ops.lanes`).

    ``d == 0`` (either sign): ``(-inf, +inf)`` if ``lo <= o <= hi`` else a miss.
    Division (not multiplication by 1/d) so that a subnormal ``d`` with ``o`` on a plane gives 0,
    not ``0 * inf``.
    """
    parallel = d == 0
    d_safe = lanes.where(parallel, 1.0, d)
    t1 = (lo - o) / d_safe
    t2 = (hi - o) / d_safe
    t_lo = lanes.where(parallel, float("-inf"), lanes.minimum(t1, t2))
    t_hi = lanes.where(parallel, float("inf"), lanes.maximum(t1, t2))
    miss = parallel & ~((o >= lo) & (o <= hi))
    return t_lo, t_hi, miss


def box_interval(o, d, lo, hi):
    """The box ``lo <= p <= hi`` along rays o + t d, in lanes: o, d, lo, hi three lanes each ->
    (t_near, t_far), misses (+inf, -inf). `intersect_box`'s body."""
    slabs = [_slab(o[i], d[i], lo[i], hi[i]) for i in range(3)]
    t_near = lanes.maximum(lanes.maximum(slabs[0][0], slabs[1][0]), slabs[2][0])
    t_far = lanes.minimum(lanes.minimum(slabs[0][1], slabs[1][1]), slabs[2][1])
    return _canonical(t_near, t_far, slabs[0][2] | slabs[1][2] | slabs[2][2])


def intersect_box(origins: Tensor, directions: Tensor, box_min, box_max) -> tuple[Tensor, Tensor]:
    """Axis-aligned box ``box_min <= p <= box_max`` (slab method).

    origins, directions [R, 3]; box_min, box_max [3] or [R, 3] -> (t_near [R], t_far [R]).
    """
    lo = _as(box_min, origins).expand_as(origins)
    hi = _as(box_max, origins).expand_as(origins)
    return box_interval(origins.unbind(-1), directions.unbind(-1), lo.unbind(-1), hi.unbind(-1))


def sphere_interval(o, d, center, radius):
    """The sphere ``|p - center| <= radius`` along rays o + t d (d unit), in lanes: o, d, center
    three lanes each, radius one -> (t_near, t_far), misses (+inf, -inf). `intersect_sphere`'s body."""
    return _sphere_roots(*_about(o, d, center), radius)


def _about(o, d, center):
    """What every sphere about `center` shares along rays o + t d (lanes): b = (o − center)·d,
    |o − center|² and the squared distance of the ray's closest approach."""
    oc = [o[i] - center[i] for i in range(3)]
    b = lanes.dot3(oc, d)
    perp = [oc[i] - b * d[i] for i in range(3)]
    return b, lanes.dot3(oc, oc), lanes.dot3(perp, perp)


def _sphere_roots(b, oc2, perp2, radius):
    """`sphere_interval` of radius `radius` from `_about`'s b, |o − center|² and closest approach²."""
    c = oc2 - radius * radius
    disc = lanes.maximum(radius * radius - perp2, -c)
    miss = disc < 0
    s = lanes.sqrt(lanes.clamp_min(disc, 0.0))
    q = -(b + lanes.where(b < 0, -s, s))  # |q| = |b| + s: no cancellation (b = ±0: the roots are ±s either way)
    q_zero = q == 0  # only when b == 0 and disc == 0, hence c == 0: both roots 0
    t2 = lanes.where(q_zero, 0.0, c / lanes.where(q_zero, 1.0, q))
    return _canonical(lanes.minimum(q, t2), lanes.maximum(q, t2), miss)


def intersect_sphere(origins: Tensor, directions: Tensor, center, radius) -> tuple[Tensor, Tensor]:
    """Sphere ``|p - center| <= radius``; directions must be unit.

    center [3] or [R, 3]; radius scalar or [R] -> (t_near [R], t_far [R]).

    With ``oc = o - c``, ``b = dot(oc, d)``, ``c = |oc|^2 - r^2``, the discriminant ``b^2 - c`` is
    evaluated in the cancellation-free form ``r^2 - |oc - b d|^2`` (Ray Tracing Gems ch. 7; equal
    for unit d), clamped below by ``-c`` (its exact lower bound, so an origin inside never misses),
    and the roots use the stable pair ``q = -b - sign(b) sqrt(disc)``, ``t = q`` and ``t = c / q``.
    """
    ctr = _as(center, origins).expand_as(origins)
    r = _as(radius, origins).expand(origins.shape[:-1])
    return sphere_interval(origins.unbind(-1), directions.unbind(-1), ctr.unbind(-1), r)


def shell_interval(o, d, center, ground, inner, outer):
    """The first stretch ahead of rays o + t d (d unit) inside the shell ``inner <= |p - center| <=
    outer`` over an opaque ground sphere of radius ``ground`` (<= inner), in lanes: o, d, center
    three lanes each, the radii one -> (t_near, t_far), misses (+inf, -inf). `intersect_shell`'s body."""
    shared = _about(o, d, center)  # the three spheres share their centre
    n_out, f_out = _sphere_roots(*shared, outer)
    n_in, f_in = _sphere_roots(*shared, inner)
    n_gr, _ = _sphere_roots(*shared, ground)
    start = lanes.clamp_min(n_out, 0.0)
    start = lanes.where((n_in <= start) & (start < f_in), f_in, start)  # starts below the layer
    end = lanes.where(n_in > start, lanes.minimum(f_out, n_in), f_out)  # comes down onto the layer's floor
    end = lanes.where(n_gr >= 0, lanes.minimum(end, n_gr), end)  # the ground hides what lies beyond
    return _canonical(start, end, n_out > f_out)


def intersect_shell(origins: Tensor, directions: Tensor, center, ground, inner, outer) -> tuple[Tensor, Tensor]:
    """The first stretch ahead of each ray inside the shell ``inner <= |p - center| <= outer``
    over an opaque ground sphere of radius ``ground`` (<= inner): a planet's cloud layer.

    center [3] or [R, 3]; ground, inner, outer scalar or [R]; directions unit -> (t_near [R],
    t_far [R]) with t_near >= 0. From below the layer: from leaving the inner sphere to leaving the
    outer one; from inside it: from 0 to the inner sphere or the outer one, whichever comes first;
    from above: from entering the outer sphere to the inner one or leaving the outer. A ray that
    meets the ground first misses (the layer beyond the horizon is hidden)."""
    radii = [_as(r, origins).expand(origins.shape[:-1]) for r in (ground, inner, outer)]
    ctr = _as(center, origins).expand_as(origins)
    return shell_interval(origins.unbind(-1), directions.unbind(-1), ctr.unbind(-1), *radii)


def slab_interval(o, d, y_min, y_max):
    """The layer ``y_min <= y <= y_max`` along rays o + t d, in lanes: o, d three lanes each ->
    (t_near, t_far), misses (+inf, -inf). `intersect_slab`'s body."""
    return _canonical(*_slab(o[1], d[1], y_min, y_max))


def intersect_slab(origins: Tensor, directions: Tensor, y_min, y_max) -> tuple[Tensor, Tensor]:
    """Horizontal layer ``y_min <= y <= y_max``.

    y_min, y_max scalars or [R] -> (t_near [R], t_far [R]). A ray with ``d.y == 0`` gets
    ``(-inf, +inf)`` inside the layer (boundary included) and a miss outside.
    """
    oy = origins[..., 1]
    return slab_interval(origins.unbind(-1), directions.unbind(-1), _as(y_min, oy).expand_as(oy), _as(y_max, oy).expand_as(oy))


def clip_to_ray(t_near: Tensor, t_far: Tensor, t_max=None) -> tuple[Tensor, Tensor, Tensor]:
    """Clip an interval to the ray ``t >= 0`` (and ``t <= t_max``, scalar or [R], if given).

    Returns ``(t0, t1, hit)`` with ``t0 = max(t_near, 0)``, ``t1 = min(t_far, t_max)`` and
    ``hit = t1 > t0`` (a zero-length touch is not a hit). For a non-hit, t0/t1 are not meaningful
    (they may be infinite); mask with ``hit``.
    """
    t0 = torch.clamp(t_near, min=0)
    t1 = t_far if t_max is None else torch.minimum(t_far, _as(t_max, t_far))
    return t0, t1, t1 > t0
