"""Voxel face shading in lanes (`ops.lanes`): the face's normal and UV, neighbour AO, rounded-voxel
refinement and texture-atlas lookup (seed 001 Steps 5–7, variant 2); the marched look
(`passes.look`) and the path tracer's surface (`path_surface`) take them."""

from __future__ import annotations

from types import SimpleNamespace
from typing import TYPE_CHECKING, Callable

import torch
from torch import Tensor

from ..geometry.sdf import rounded_box_lanes
from ..ops import lanes
from ..ops.mathops import pow_

if TYPE_CHECKING:
    from ..schema.batch import Stacked

__all__ = ["ao_lanes", "atlas_lanes", "atlas_table", "face_lanes", "face_uv_lanes", "rounded_lanes", "texel_lanes", "vertex_ao", "voxel_ao"]


def face_lanes(axis, d: list) -> list:
    """The outward normal (three lanes) of the face entered on `axis` (int lanes) by rays along d
    (three lanes): −sign(d) on that axis (the seed's ``-mask * rayStep``; −0 where d is 0, as
    torch's −sign), 0 on the others."""
    return [lanes.where(axis == c, lanes.where(d[c] > 0.0, -1.0, lanes.where(d[c] < 0.0, 1.0, d[c] * -0.0)), 0.0)
            for c in range(3)]  # (d · −0: the lanes' float type, where two numbers would give torch's default)


def face_uv_lanes(local: list, axis) -> tuple:
    """The face UV (two lanes) of a hit at cell-local coordinates `local` (three lanes, in [0, 1])
    on a face on `axis` (int lanes): x faces (y, z), y faces (z, x), z faces (x, y) (seed Step 6)."""
    u = lanes.where(axis == 0, local[1], lanes.where(axis == 1, local[2], local[0]))
    v = lanes.where(axis == 0, local[2], lanes.where(axis == 1, local[0], local[1]))
    return u, v


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


def texel_lanes(table: list, base, height, width, tiles, material, u, v) -> list:
    """The nearest texel of a texture atlas, in lanes (`ops.lanes`: torch columns, or Dr.Jit arrays):
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


def atlas_table(texture: Stacked) -> SimpleNamespace:
    """A batch's texture atlases as `atlas_lanes` reads them, built once a render: every scene's
    atlas flattened one after the other (three float32 channels, values 0-255), each one's first
    texel, height, width (B,) and tiles a side (B,)."""
    atlases = [torch.as_tensor(a) for a in texture.atlas]
    return SimpleNamespace(channels=[torch.cat([a[..., c].reshape(-1) for a in atlases]).float() for c in range(3)],
                           starts=torch.tensor([0] + [a.shape[0] * a.shape[1] for a in atlases[:-1]]).cumsum(0).to(torch.int32),
                           height=torch.tensor([float(a.shape[0]) for a in atlases]),
                           width=torch.tensor([float(a.shape[1]) for a in atlases]),
                           tiles=torch.as_tensor(texture.tiles).float())


def atlas_lanes(atlas: SimpleNamespace, s: Tensor, per_lane, ints, floats):
    """The scenes' texture atlases (`atlas_table`) as lanes of rays of scenes `s` [n] (`per_lane`:
    per scene -> lanes; `ints`, `floats`: a tensor -> lanes): texel(material, u, v) -> three lanes
    (`texel_lanes`)."""
    table = [floats(c) for c in atlas.channels]
    base = ints(atlas.starts.to(s.device).index_select(0, s))
    height, width, tiles = (per_lane(x.to(s.device)) for x in (atlas.height, atlas.width, atlas.tiles))
    return lambda material, u, v: texel_lanes(table, base, height, width, tiles, material, u, v)


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
