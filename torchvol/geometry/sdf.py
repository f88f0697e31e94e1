"""Signed distance functions and CSG, as plain functions of points (negative inside).

Primitives take points ``p [N, 3]`` (already in the primitive's frame: subtract its centre first)
and return ``[N]``; they follow the seeds' GLSL so that float32 results match a shader:

* ``sd_sphere(p, r) = length(p) - r``
* ``sd_box(p, b) = min(max(d.x, max(d.y, d.z)), 0) + length(max(d, 0))`` with ``d = |p| - b``
* ``sd_rounded_box(p, b, r) = length(max(|p| - b + r, 0)) - r`` (the seed's rounded voxel: b = 0.5)

CSG on distance values ``[N]``: ``union = min``, ``intersection = max``, ``subtraction(a, b) =
max(a, -b)`` (a with b carved out; the seed's ``max(-sdSphere, sdBox)``).

`evaluate(tree, p)` evaluates a scene SDF tree (the ``voxels.occupancy.sdf`` schema: one key per
node, ``sphere``/``box``/``rounded_box`` leaves, ``union``/``intersection`` lists and
``subtraction = {a, b}``) at points ``p [N, 3]``.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from ..ops import lanes

__all__ = ["sd_sphere", "sd_box", "sd_rounded_box", "rounded_box_lanes", "union", "intersection", "subtraction", "evaluate"]


def _length(v: Tensor) -> Tensor:
    """GLSL length: sqrt(dot(v, v)) over the last axis (no hypot rescaling, as llvmpipe does)."""
    return torch.sqrt((v * v).sum(-1))


def sd_sphere(p: Tensor, radius) -> Tensor:
    """Sphere at the origin. p [N, 3]; radius scalar or [N] -> [N]."""
    return _length(p) - radius


def sd_box(p: Tensor, half_size) -> Tensor:
    """Box at the origin with half extents `half_size` ([3], [N, 3] or scalar). p [N, 3] -> [N]."""
    d = p.abs() - torch.as_tensor(half_size, dtype=p.dtype, device=p.device)
    inside = torch.clamp(torch.maximum(d[..., 0], torch.maximum(d[..., 1], d[..., 2])), max=0.0)
    return inside + _length(d.clamp_min(0.0))


def sd_rounded_box(p: Tensor, half_size, radius) -> Tensor:
    """Box with edges rounded by `radius` (scalar or [N]); half_size [3], [N, 3] or scalar. -> [N]
    (`rounded_box_lanes` on p's columns)."""
    r = torch.as_tensor(radius, dtype=p.dtype, device=p.device)
    b = torch.as_tensor(half_size, dtype=p.dtype, device=p.device).expand(p.shape)
    return rounded_box_lanes(list(p.unbind(-1)), list(b.unbind(-1)), r)


def rounded_box_lanes(p: list, half: list, radius):
    """`sd_rounded_box` in lanes (`ops.lanes`): points p and half sizes `half` (three lanes or
    numbers each), `radius` a lane or number: length(max(|p| − b + r, 0)) − r."""
    q = [lanes.clamp_min(lanes.abs(p[i]) - half[i] + radius, 0.0) for i in range(3)]
    return lanes.length3(*q) - radius


def union(*ds: Tensor) -> Tensor:
    """The union of signed distances `ds` (each [n]): their minimum [n]."""
    out = ds[0]
    for d in ds[1:]:
        out = torch.minimum(out, d)
    return out


def intersection(*ds: Tensor) -> Tensor:
    """The intersection of signed distances `ds` (each [n]): their maximum [n]."""
    out = ds[0]
    for d in ds[1:]:
        out = torch.maximum(out, d)
    return out


def subtraction(a: Tensor, b: Tensor) -> Tensor:
    """`a` with `b` carved out: max(a, -b)."""
    return torch.maximum(a, -b)


def _get(node: Any, key: str):
    return node.get(key) if isinstance(node, dict) else getattr(node, key, None)


def evaluate(tree: Any, p: Tensor) -> Tensor:
    """A scene SDF tree (pydantic `SdfNode` or the equivalent dict) at points p [N, 3] -> [N]."""
    for kind in ("sphere", "box", "rounded_box", "union", "intersection", "subtraction"):
        node = _get(tree, kind)
        if node is None:
            continue
        if kind in ("union", "intersection"):
            ds = [evaluate(child, p) for child in node]
            return union(*ds) if kind == "union" else intersection(*ds)
        if kind == "subtraction":
            return subtraction(evaluate(_get(node, "a"), p), evaluate(_get(node, "b"), p))
        centre = torch.as_tensor(_get(node, "center"), dtype=p.dtype, device=p.device)
        q = p - centre
        if kind == "sphere":
            return sd_sphere(q, _get(node, "radius"))
        if kind == "box":
            return sd_box(q, _get(node, "half_size"))
        return sd_rounded_box(q, _get(node, "half_size"), _get(node, "radius"))
    raise ValueError(f"not an SDF node: {tree!r}")
