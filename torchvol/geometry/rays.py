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

__all__ = ["intersect_box", "intersect_sphere", "intersect_slab", "clip_to_ray"]


def _as(x, like: Tensor) -> Tensor:
    return torch.as_tensor(x, dtype=like.dtype, device=like.device)


def _canonical(t_near: Tensor, t_far: Tensor, miss: Tensor) -> tuple[Tensor, Tensor]:
    """Set misses (and empty/infinite-degenerate intervals) to (+inf, -inf)."""
    miss = miss | ~(t_near <= t_far) | (t_near == float("inf")) | (t_far == float("-inf"))
    inf = torch.full_like(t_near, float("inf"))
    return torch.where(miss, inf, t_near), torch.where(miss, -inf, t_far)


def _slab(o: Tensor, d: Tensor, lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Per-component slab interval: (t_lo, t_hi, miss) elementwise, NaN-free.

    ``d == 0`` (either sign): ``(-inf, +inf)`` if ``lo <= o <= hi`` else a miss.
    Division (not multiplication by 1/d) so that a subnormal ``d`` with ``o`` on a plane gives 0,
    not ``0 * inf``.
    """
    parallel = d == 0
    d_safe = torch.where(parallel, torch.ones_like(d), d)
    t1 = (lo - o) / d_safe
    t2 = (hi - o) / d_safe
    t_lo = torch.minimum(t1, t2)
    t_hi = torch.maximum(t1, t2)
    inside = (o >= lo) & (o <= hi)
    inf = torch.full_like(t_lo, float("inf"))
    t_lo = torch.where(parallel, -inf, t_lo)
    t_hi = torch.where(parallel, inf, t_hi)
    miss = parallel & ~inside
    return t_lo, t_hi, miss


def intersect_box(origins: Tensor, directions: Tensor, box_min, box_max) -> tuple[Tensor, Tensor]:
    """Axis-aligned box ``box_min <= p <= box_max`` (slab method).

    origins, directions [R, 3]; box_min, box_max [3] or [R, 3] -> (t_near [R], t_far [R]).
    """
    lo = _as(box_min, origins)
    hi = _as(box_max, origins)
    t_lo, t_hi, miss = _slab(origins, directions, lo, hi)
    t_near = t_lo.amax(dim=-1)
    t_far = t_hi.amin(dim=-1)
    return _canonical(t_near, t_far, miss.any(dim=-1))


def intersect_sphere(origins: Tensor, directions: Tensor, center, radius) -> tuple[Tensor, Tensor]:
    """Sphere ``|p - center| <= radius``; directions must be unit.

    center [3] or [R, 3]; radius scalar or [R] -> (t_near [R], t_far [R]).

    With ``oc = o - c``, ``b = dot(oc, d)``, ``c = |oc|^2 - r^2``, the discriminant ``b^2 - c`` is
    evaluated in the cancellation-free form ``r^2 - |oc - b d|^2`` (Ray Tracing Gems ch. 7; equal
    for unit d), clamped below by ``-c`` (its exact lower bound, so an origin inside never misses),
    and the roots use the stable pair ``q = -b - sign(b) sqrt(disc)``, ``t = q`` and ``t = c / q``.
    """
    ctr = _as(center, origins)
    r = _as(radius, origins)
    oc = origins - ctr
    b = (oc * directions).sum(-1)
    c = (oc * oc).sum(-1) - r * r
    perp = oc - b[..., None] * directions
    disc = r * r - (perp * perp).sum(-1)
    disc = torch.maximum(disc, -c)
    miss = disc < 0
    s = torch.sqrt(torch.clamp(disc, min=0))
    q = -(b + torch.copysign(s, b))  # |q| = |b| + s: no cancellation
    q_zero = q == 0  # only when b == 0 and disc == 0, hence c == 0: both roots 0
    q_safe = torch.where(q_zero, torch.ones_like(q), q)
    t1 = q
    t2 = torch.where(q_zero, torch.zeros_like(q), c / q_safe)
    t_near = torch.minimum(t1, t2)
    t_far = torch.maximum(t1, t2)
    return _canonical(t_near, t_far, miss)


def intersect_shell(origins: Tensor, directions: Tensor, center, ground, inner, outer) -> tuple[Tensor, Tensor]:
    """The first stretch ahead of each ray inside the shell ``inner <= |p - center| <= outer``
    over an opaque ground sphere of radius ``ground`` (<= inner): a planet's cloud layer.

    center [3] or [R, 3]; ground, inner, outer scalar or [R]; directions unit -> (t_near [R],
    t_far [R]) with t_near >= 0. From below the layer: from leaving the inner sphere to leaving the
    outer one; from inside it: from 0 to the inner sphere or the outer one, whichever comes first;
    from above: from entering the outer sphere to the inner one or leaving the outer. A ray that
    meets the ground first misses (the layer beyond the horizon is hidden)."""
    n_out, f_out = intersect_sphere(origins, directions, center, outer)
    n_in, f_in = intersect_sphere(origins, directions, center, inner)
    n_gr, _ = intersect_sphere(origins, directions, center, ground)
    start = n_out.clamp_min(0.0)
    start = torch.where((n_in <= start) & (start < f_in), f_in, start)  # starts below the layer
    end = torch.where(n_in > start, torch.minimum(f_out, n_in), f_out)  # comes down onto the layer's floor
    end = torch.where(n_gr >= 0, torch.minimum(end, n_gr), end)  # the ground hides what lies beyond
    return _canonical(start, end, n_out > f_out)


def intersect_slab(origins: Tensor, directions: Tensor, y_min, y_max) -> tuple[Tensor, Tensor]:
    """Horizontal layer ``y_min <= y <= y_max``.

    y_min, y_max scalars or [R] -> (t_near [R], t_far [R]). A ray with ``d.y == 0`` gets
    ``(-inf, +inf)`` inside the layer (boundary included) and a miss outside.
    """
    oy = origins[..., 1]
    dy = directions[..., 1]
    t_lo, t_hi, miss = _slab(oy, dy, _as(y_min, oy), _as(y_max, oy))
    return _canonical(t_lo, t_hi, miss)


def clip_to_ray(t_near: Tensor, t_far: Tensor, t_max=None) -> tuple[Tensor, Tensor, Tensor]:
    """Clip an interval to the ray ``t >= 0`` (and ``t <= t_max``, scalar or [R], if given).

    Returns ``(t0, t1, hit)`` with ``t0 = max(t_near, 0)``, ``t1 = min(t_far, t_max)`` and
    ``hit = t1 > t0`` (a zero-length touch is not a hit). For a non-hit, t0/t1 are not meaningful
    (they may be infinite); mask with ``hit``.
    """
    t0 = torch.clamp(t_near, min=0)
    t1 = t_far if t_max is None else torch.minimum(t_far, _as(t_max, t_far))
    return t0, t1, t1 > t0
