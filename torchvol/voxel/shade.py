"""Voxel face shading as plain functions: face normal, face UV, three-tone faces, neighbour AO,
Lambert sun, rounded-voxel refinement and texture-atlas lookup (seed 001 Steps 5–8, variant 2)."""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from ..geometry.sdf import rounded_box_lanes
from ..ops import lanes
from ..ops.mathops import pow_

__all__ = ["ao_lanes", "face_normal", "face_uv", "face_tone", "vertex_ao", "voxel_ao", "lambert", "atlas_sample", "rounded_lanes",
           "texel_lanes"]


def face_normal(axis: Tensor, directions: Tensor) -> Tensor:
    """Outward normal [N, 3] of the face entered along `axis` [N] by rays `directions` [N, 3]:
    −sign(d_axis) on that axis (the seed's ``-mask * rayStep``)."""
    n = torch.zeros_like(directions)
    s = -torch.sign(directions.gather(1, axis[:, None]))
    return n.scatter_(1, axis[:, None], s)


def face_uv(local: Tensor, axis: Tensor) -> Tensor:
    """Face UV [N, 2] from voxel-local hit coordinates `local` [N, 3] (hit − cell, in [0, 1]) of a face
    on `axis` [N]: x faces (y, z), y faces (z, x), z faces (x, y) — seed Step 6."""
    a1 = (axis + 1) % 3
    a2 = (axis + 2) % 3
    return torch.stack([local.gather(1, a1[:, None])[:, 0], local.gather(1, a2[:, None])[:, 0]], dim=1)


def face_tone(axis: Tensor, tones: Tensor) -> Tensor:
    """Three-tone face brightness [N] from per-ray tones [N, 3] (x, y, z faces) — seed Step 5."""
    return tones.gather(1, axis[:, None])[:, 0]


def vertex_ao(side1, side2, corner):
    """Occlusion of one face vertex from its two edge neighbours and its corner (0/1 floats, lanes)."""
    return (side1 + side2 + lanes.maximum(corner, side1 * side2)) / 3.0


def ao_lanes(occupied: Callable, cell, normal, axis, u, v, gamma):
    """Seed Step 7: neighbour AO at hit faces, in lanes (`ops.lanes`: torch columns in `voxel_ao`,
    Dr.Jit arrays in `ao_kernel`). `cell`, `normal`: three int lanes each (the hit cell, the face's
    outward normal); `axis` int (the face's axis); `u`, `v` the face UV; `gamma`; occupied(x, y, z)
    -> 1.0 / 0.0 at int cells. The 4 edge and 4 corner neighbours of the empty cell in front of the
    face, ``pos = cell + normal``, stepped along d1 = e[(axis+1)%3] and d2 = e[(axis+2)%3];
    ao = mix(mix(a.z, a.w, u), mix(a.y, a.x, u), v) ^ gamma with a = 1 − vertexAo per vertex."""
    pos = [c + n for c, n in zip(cell, normal)]
    a1, a2 = lanes.where(axis == 2, 0, axis + 1), lanes.where(axis == 0, 2, axis - 1)
    d1, d2 = [lanes.to_int32(a1 == i) for i in range(3)], [lanes.to_int32(a2 == i) for i in range(3)]

    def at(s1: int, s2: int):
        return occupied(*(pos[i] + s1 * d1[i] + s2 * d2[i] for i in range(3)))

    sx, sy, sz, sw = at(1, 0), at(0, 1), at(-1, 0), at(0, -1)
    cx, cy, cz, cw = at(1, 1), at(-1, 1), at(-1, -1), at(1, -1)
    ax = 1.0 - vertex_ao(sx, sy, cx)
    ay = 1.0 - vertex_ao(sy, sz, cy)
    az = 1.0 - vertex_ao(sz, sw, cz)
    aw = 1.0 - vertex_ao(sw, sx, cw)
    return pow_(lanes.lerp(lanes.lerp(az, aw, u), lanes.lerp(ay, ax, u), v), gamma)


def voxel_ao(occupied: Callable[[Tensor], Tensor], cell: Tensor, normal: Tensor, axis: Tensor, uv: Tensor, *,
             gamma: float | Tensor = 1.0) -> Tensor:
    """`ao_lanes` on torch columns: occupied(cells [M, 3] long) -> [M] bool or 0/1; cell [N, 3] long;
    normal [N, 3]; axis [N]; uv [N, 2] face UV. -> [N]."""
    return ao_lanes(lambda x, y, z: occupied(torch.stack([x, y, z], 1)).to(uv.dtype), cell.unbind(1),
                    normal.to(torch.long).unbind(1), axis, uv[:, 0], uv[:, 1], gamma)


def lambert(normal: Tensor, sun: Tensor) -> Tensor:
    """max(dot(n, l), 0) [N] for normals and sun directions [N, 3] (towards the sun)."""
    return (normal * sun).sum(dim=1).clamp_min(0.0)


def atlas_sample(atlas: Tensor, tiles: int, material: Tensor, uv: Tensor) -> Tensor:
    """Nearest texel [N, 3] in [0, 1] of a (H, W, 3) uint8 atlas: material m uses tile m − 1
    (row-major from the top left), u to the right, v up (uv [N, 2] in [0, 1]). `texel_lanes` on
    torch columns."""
    H, W = atlas.shape[0], atlas.shape[1]
    table = [atlas[..., c].reshape(-1).to(uv.dtype) for c in range(3)]
    return torch.stack(texel_lanes(table, 0, H, W, tiles, material, uv[:, 0], uv[:, 1]), dim=1)


def texel_lanes(table: list, base, height, width, tiles, material, u, v) -> list:
    """`atlas_sample` in lanes (`ops.lanes`: torch columns, or the path kernel's Dr.Jit arrays):
    `table` the atlases' three channels flattened row-major (values 0–255), `base` (int) the
    atlas's first texel, its `height`, `width` and `tiles` a side (numbers or lanes), `material`
    (int), the face UV `u`, `v`. -> three lanes in [0, 1]."""
    tile = lanes.to_float(lanes.clamp_min(material - 1, 0), u)
    row = lanes.floor(tile / tiles)
    col = tile - row * tiles
    x = lanes.minimum(lanes.clamp_min(lanes.floor((col + lanes.clamp(u, 0.0, 1.0)) / tiles * width), 0.0), width - 1.0)
    y = lanes.minimum(lanes.clamp_min(lanes.floor((row + 1.0 - lanes.clamp(v, 0.0, 1.0)) / tiles * height), 0.0), height - 1.0)
    at = base + lanes.to_int32(y * width + x)
    return [lanes.gather(c, at) / 255.0 for c in table]


def rounded_lanes(local: list, direction: list, radius, *, steps: int, threshold) -> tuple:
    """Seed variant 2 inside a hit voxel, in lanes (`ops.lanes`; `walk.rounded_walk` takes it):
    `steps` sphere-tracing steps of sdRoundedBox(p, 0.5, radius) from `local` along `direction`
    (three lanes each), converged where h < `threshold`. -> (converged, advance (voxel units), the
    unit normal (three lanes))."""
    p, advance = list(local), radius * 0.0
    done = advance > 0.0
    for _ in range(steps):
        h = rounded_box_lanes(p, [0.5] * 3, radius)
        done = done | (h < threshold)
        step = lanes.where(done, 0.0, lanes.clamp_min(h, 0.0))
        p = [p[i] + direction[i] * step for i in range(3)]
        advance = advance + step
    q = [lanes.clamp_min(lanes.abs(c) - 0.5 + radius, 0.0) * lanes.where(c > 0.0, 1.0, lanes.where(c < 0.0, -1.0, 0.0))
         for c in p]
    size = lanes.length3(*q)
    # inside the inner box (radius 0, or an entry point rounded a hair inside the cube) q is 0: the
    # normal is then the face the point is nearest, the cube's (it was 0: a black face)
    a = [lanes.abs(c) for c in p]
    face = [(a[0] >= a[1]) & (a[0] >= a[2]), (a[1] > a[0]) & (a[1] >= a[2]), (a[2] > a[0]) & (a[2] > a[1])]
    return done, advance, [lanes.where(size > 0.0, q[i] / lanes.clamp_min(size, 1e-30),
                                       lanes.where(face[i], lanes.where(p[i] < 0.0, -1.0, 1.0), 0.0)) for i in range(3)]
