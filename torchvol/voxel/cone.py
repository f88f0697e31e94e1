"""Voxel cone tracing (`voxels.gi = { method = "cone", cones, aperture, steps, max_distance, ao, lod }`,
seed 001 Variant 4): one-bounce diffuse GI and AO from a 3D mip chain instead of path-traced rays.

**The mip chain** (`build_mips`, once per render, pass `voxels.gi.mips`): level 0 holds, per cell
of each scene's grid zero-padded to a cube of 2^k cells, its opacity (1 occupied, 0 empty) and, for
cells with an exposed face, their radiance: the direct light the faces reflect (albedo · Σ
irradiance · cos · shadow visibility, plus emission: what a path-traced bounce sees at a hit),
averaged over the cell's exposed faces (an isotropic voxel: a corner cell looks the same from every
side). Each level above is the 2×2×2 mean of the one below (`avg_pool3d`), down to one cell, whose
value is therefore the mean of the base; a coarse cell's colour is the mean radiance of the
surfaces in it, its opacity the share of occupied cells.

**The cones** (`trace_cones`, pass `voxels.gi.cones`): from each primary hit, `cones` directions
of equal weight partitioning the cosine-weighted hemisphere about the face normal (`cone_directions`:
one along the normal, the rest on a ring, Malley's disk-to-hemisphere map). Each cone of half-angle
`aperture` starts one voxel off the face and marches front to back (the seed's `traceCone`): at
distance t (from t = 1 voxel) its radius is r = max(½, t·tan(aperture)) voxels; it samples the level
whose cells are r wide (lod = log2 r, trilinear in space and linear between levels:
`F.grid_sample`), accumulates radiance C += (1 − A)·α·c and occlusion A += (1 − A)·α, and steps on
by r, so the samples tile its axis. A cone ends when it is opaque (A > 0.99), leaves the grid,
passes `max_distance` or has taken `steps` samples; its unoccluded part sees the sky: L_k = C_k +
(1 − A_k)·sky(d_k). The incoming radiance is the mean over cones, the path tracer's bounces = 1
estimate with cones for rays: it goes to `_lit` in place of the ambient, so a closed room of albedo
a emitting e sees about e·(1 + a).

**Cone AO** (`ao = true`): the cones' mean visibility 1 − A multiplies the surface's albedo, as the
neighbour AO (`voxels.ao`) does, and is the `ao` AOV.

**Distance LOD** (`lod = { near, far, cones, aperture }`): hits further from the camera than
`near` widen their cones towards `lod.aperture` (reached at `far`: coarser mips, fewer steps), and
hits beyond `far` trace only `lod.cones` cones.

The approximation: isotropic cells (a thin wall glows on both sides), opacity averaged over
coarse cells (light leaks through thin walls, and a cone sees the surface it starts on at coarse
levels), one bounce. Cost: one mip build (a DDA shadow ray per exposed face per light where
`voxels.shadow` is set, then the pooling), then cones × steps trilinear fetches per hit pixel (two
levels each), no DDA traversal.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from types import SimpleNamespace
from typing import Annotated, Literal, Union

import torch
import torch.nn.functional as F
from pydantic import Discriminator, Field, Tag
from torch import Tensor

from ..geometry.scatter import basis
from ..ops import lanes, mathops
from ..schema.models import Strict
from .gi import DistanceLOD, VoxelGI

__all__ = ["ConeLOD", "VoxelCone", "VoxelGIs", "build_mips", "cone_ao", "cone_directions", "cone_step", "default_aperture",
           "face_cells", "mip_table", "trace_cones"]

OPAQUE = 0.99  # a cone stops when its occlusion passes this
CHANNELS = 5  # radiance · surface (3), surface, opacity
OFFSET = 1.0  # a cone starts this many voxels off the face (less self-occlusion at coarse levels)


class ConeLOD(DistanceLOD):
    """Distance LOD of the cones: beyond `near` (world distance from the camera) the half-angle
    widens linearly to `aperture` at `far`; beyond `far` only `cones` cones are traced."""

    cones: int = Field(3, ge=1, le=64)
    aperture: float = Field(50.0, gt=0.0, lt=90.0)


class VoxelCone(Strict):
    """Cone-traced one-bounce diffuse GI (and AO) from a mip chain of the voxels' opacity and radiance."""

    method: Literal["cone"] = "cone"
    cones: int = Field(6, ge=1, le=64)
    aperture: float | None = Field(None, gt=0.0, lt=90.0, description="cone half-angle, degrees; None: the cones "
                                   "cover the hemisphere (cos = 1 - 1/cones, at most 60)")
    steps: int = Field(48, ge=1, le=4096)  # samples per cone at most
    max_distance: float = Field(1e9, gt=0.0)  # world units a cone travels at most
    ao: bool = False  # the cones' visibility multiplies the albedo (and is the `ao` AOV)
    lod: ConeLOD | None = None


def _method(value) -> str:
    return value.get("method", "path") if isinstance(value, dict) else getattr(value, "method", "path")


# `voxels.gi`: a path tracer or cones, chosen by `method` (path where it is absent)
VoxelGIs = Annotated[Union[Annotated[VoxelGI, Tag("path")], Annotated[VoxelCone, Tag("cone")]], Discriminator(_method)]


def cone_ao(voxels) -> bool:
    """Whether a batch's `voxels` (its `Stacked` view) ask for cone AO (`voxels.gi.ao` with cones)."""
    return voxels.gi is not None and voxels.gi.method == "cone" and voxels.gi.ao


def default_aperture(cones: int) -> float:
    """The half-angle (degrees) at which `cones` cones' solid angles add up to the hemisphere's, at
    most 60° (one cone would be the whole hemisphere: the top level at its first sample)."""
    return min(60.0, math.degrees(math.acos(1.0 - 1.0 / cones)))


def cone_directions(normal: Tensor, count: int) -> Tensor:
    """`count` unit directions [n, count, 3] about unit normals [n, 3] that split the
    cosine-weighted hemisphere into parts of equal weight: the disk of Malley's map cut into a
    centre of area 1/count (its cone along the normal) and a ring of count − 1 equal sectors, each
    cone through the sector's area-median radius."""
    dt = normal.dtype
    if count == 1:
        return normal[:, None, :].clone()
    r = math.sqrt((1.0 + 1.0 / count) / 2.0)
    phi = 2.0 * math.pi * torch.arange(count - 1, dtype=dt, device=normal.device) / (count - 1)
    local = torch.cat([torch.tensor([[0.0, 0.0, 1.0]], dtype=dt, device=normal.device),
                       torch.stack([r * torch.cos(phi), r * torch.sin(phi),
                                    torch.full_like(phi, math.sqrt(1.0 - r * r))], dim=1)])  # [count, 3]
    t, bt = (torch.stack(v, dim=1) for v in basis(lanes.columns(normal)))
    return local[None, :, 0:1] * t[:, None] + local[None, :, 1:2] * bt[:, None] + local[None, :, 2:3] * normal[:, None]


FACES = [(axis, sign) for axis in range(3) for sign in (-1, 1)]


def face_cells(occupied: Tensor) -> list[tuple[int, int, Tensor]]:
    """The exposed faces of an occupancy (Z, Y, X) bool: per face direction (axis 0/1/2 = x/y/z,
    sign ±1 its outward normal) the array indices [m, 3] (x, y, z) of occupied cells whose
    neighbour that way is empty (outside the array counts as empty)."""
    out = []
    for axis, sign in FACES:
        dim = 2 - axis  # the array's (z, y, x) layout
        neighbour = torch.roll(occupied, -sign, dims=dim)
        edge = [slice(None)] * 3
        edge[dim] = -1 if sign > 0 else 0
        neighbour[tuple(edge)] = False
        zyx = (occupied & ~neighbour).nonzero()
        out.append((axis, sign, zyx.flip(1)))
    return out


def build_mips(opacity: Tensor, radiance: Tensor, surface: Tensor) -> list[Tensor]:
    """The mip chain of a base level: opacity (B, Z, Y, X) in [0, 1], radiance (B, 3, Z, Y, X) and
    surface (B, Z, Y, X) (1 where a cell has an exposed face, whose radiance it holds), zero-padded
    to cubes of side P = 2^k ≥ the largest side -> levels (B, 5, P/2^l, P/2^l, P/2^l), l = 0 … k,
    channels radiance · surface (3), surface, opacity; each level the 2×2×2 mean of the one below.
    A coarse cell's colour is then the mean radiance of the surfaces in it (cells inside a solid
    block block light but show none), its opacity the share of occupied cells."""
    B, Z, Y, X = opacity.shape
    P = 1 << max(0, math.ceil(math.log2(max(Z, Y, X))))
    base = opacity.new_zeros(B, CHANNELS, P, P, P)
    base[:, :3, :Z, :Y, :X] = radiance * surface[:, None]
    base[:, 3, :Z, :Y, :X] = surface
    base[:, 4, :Z, :Y, :X] = opacity
    levels = [base]
    while levels[-1].shape[-1] > 1:
        levels.append(F.avg_pool3d(levels[-1], 2))
    return levels


def mip_table(levels: list[Tensor]) -> tuple[Tensor, list[int], list[int]]:
    """The mip chain as one flat table, channel last: level l's entry (b, z, y, x, c) at
    ``offsets[l] + (((b·P_l + z)·P_l + y)·P_l + x)·5 + c`` -> (table [M], offsets, sizes P_l)."""
    flat = [level.permute(0, 2, 3, 4, 1).reshape(-1) for level in levels]
    offsets = [0]
    for f in flat[:-1]:
        offsets.append(offsets[-1] + f.shape[0])
    return torch.cat(flat), offsets, [level.shape[-1] for level in levels]


def _fetch_lanes(table, gather_level: Callable, lvl, g, s):
    """Trilinear samples (five lanes) of level `lvl` (int lanes) at normalised points `g` (three
    lanes, x, y, z in [-1, 1] over the padded cube) of scenes `s` (int lanes), zero outside: the
    `F.grid_sample` of align_corners=False and zero padding, in lanes. `gather_level(lvl)` -> (its
    offset (int lanes), its size P (int lanes))."""
    offset, size = gather_level(lvl)
    fsize = lanes.to_float(size, g[0])
    ix = [((c + 1.0) * fsize - 1.0) * 0.5 for c in g]
    i0 = [lanes.to_int32(lanes.floor(x)) for x in ix]
    w1 = [x - lanes.floor(x) for x in ix]
    out = [0.0] * CHANNELS
    for corner in range(8):
        idx = [i0[a] + ((corner >> a) & 1) for a in range(3)]
        w = [w1[a] if (corner >> a) & 1 else 1.0 - w1[a] for a in range(3)]
        inside = ((idx[0] >= 0) & (idx[0] < size) & (idx[1] >= 0) & (idx[1] < size) & (idx[2] >= 0)
                  & (idx[2] < size))
        at = offset + (((s * size + idx[2]) * size + idx[1]) * size + idx[0]) * CHANNELS
        at = lanes.where(inside, at, 0)
        weight = lanes.where(inside, w[0] * w[1] * w[2], 0.0)
        for c in range(CHANNELS):
            out[c] = out[c] + weight * lanes.gather(table, at + c)
    return out


def cone_step(state: list, ray: SimpleNamespace, mips: SimpleNamespace) -> list:
    """One sample of every cone, in lanes (`ops.lanes`: torch columns in `trace_cones`, Dr.Jit
    arrays in `shade_kernel.cones_kernel`): state (t, occlusion, the radiance's three lanes,
    alive); `ray` its origin and direction (three lanes each, in cells of the padded cube), scene
    s, ratio, max_t; `mips` the chain (`mip_table`'s table, gather_level, top, size P). -> the
    state after it (a finished cone kept as it was)."""
    t, occ, cr, cg, cb, alive = state
    radius = lanes.clamp_min(0.5 * t * ray.ratio, 0.5)  # a cone is at least a voxel wide
    p = [o + t * d for o, d in zip(ray.o, ray.d)]
    # the level whose cells are as wide as the radius, the step: samples tile the cone's axis
    lod = lanes.clamp(lanes.log2(radius), 0.0, float(mips.top))
    lo = lanes.to_int32(lanes.clamp_max(lanes.floor(lod), float(max(mips.top - 1, 0))))
    frac = lod - lanes.to_float(lo, lod)
    g = [c * (2.0 / mips.size) - 1.0 for c in p]
    v = _fetch_lanes(mips.table, mips.gather_level, lo, g, ray.s)
    if mips.top > 0:
        v1 = _fetch_lanes(mips.table, mips.gather_level, lo + 1, g, ray.s)
        v = [a + frac * (b - a) for a, b in zip(v, v1)]
    alpha = lanes.clamp(v[4], 0.0, 1.0)
    # a step shorter than the (level-0) cell crosses that share of it
    alpha = lanes.where(radius >= 1.0, alpha, 1.0 - mathops.pow_(1.0 - alpha, radius))
    surface = lanes.clamp_min(v[3], 1e-12)
    weight = (1.0 - occ) * alpha
    lit = [c + weight * (v[k] / surface) for k, c in enumerate((cr, cg, cb))]
    occ_new, t_new = occ + weight, t + radius
    # past the cube (outside is empty: open to the sky), or wider than it (the top level's one cell)
    inside = radius <= mips.size
    for c in p:
        inside = inside & (c >= 0.0) & (c <= mips.size)
    keep = alive & (occ_new < OPAQUE) & inside & (t_new < ray.max_t)
    return [lanes.where(alive, t_new, t), lanes.where(alive, occ_new, occ),
            *(lanes.where(alive, new, old) for new, old in zip(lit, (cr, cg, cb))), keep]


def trace_cones(levels: list[Tensor], origin: Tensor, direction: Tensor, s: Tensor, ratio: Tensor, *,
                steps: int, max_t: Tensor) -> tuple[Tensor, Tensor]:
    """March cones front to back through the mip chain (`cone_step` on torch columns, `steps`
    samples at most). origin [n, 3] in cells of the padded cube (its (0, 0, 0) corner at 0),
    direction [n, 3] unit, s [n] scenes, ratio [n] the diameter per unit distance (2·tan(half-angle)),
    max_t [n] the longest distance (cells) -> (radiance [n, 3] the accumulated radiance, occlusion
    [n] in [0, 1])."""
    table, offsets, sizes = mip_table(levels)
    offsets_t, sizes_t = (torch.tensor(x, device=s.device) for x in (offsets, sizes))
    mips = SimpleNamespace(table=table, top=len(levels) - 1, size=levels[0].shape[-1],
                           gather_level=lambda lvl: (offsets_t[lvl.long()], sizes_t[lvl.long()]))
    ray = SimpleNamespace(o=origin.unbind(1), d=direction.unbind(1), s=s, ratio=ratio, max_t=max_t)
    n = origin.shape[0]
    state = [torch.ones(n, dtype=origin.dtype, device=origin.device), origin.new_zeros(n), origin.new_zeros(n),
             origin.new_zeros(n), origin.new_zeros(n), torch.ones(n, dtype=torch.bool, device=origin.device)]
    for _ in range(steps):  # the seed's t = 1: the first sample a voxel out
        if not bool(state[5].any()):
            break
        state = cone_step(state, ray, mips)
    return torch.stack(state[2:5], 1), state[1]
