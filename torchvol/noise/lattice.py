"""Procedural noise on tensors: lattice hash, value, gradient (Perlin), Worley, texture noise, fBm.

Every function is a plain, vectorised function of its tensor arguments (no Python loop over
points, no global RNG): seeds are integers. Points are ``p: [N, 3]`` (any float dtype, any device;
results take ``p``'s dtype and device) and results are ``[N]``.

`texture_noise` is the seeds' texture-based value noise (template 002: ``noise()`` sampling a
256x256 RGBA8 texture with the ``(37, 239)`` z trick). It reproduces Mesa llvmpipe's RGBA8
bilinear filter bit for bit (see its docstring), so float32 results equal the GLSL run on llvmpipe.
"""

from __future__ import annotations

import functools
import math
import weakref
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from ..ops import lanes
from ..ops.mathops import take_rows

__all__ = [
    "hash3",
    "hash3_lanes",
    "int32_bits",
    "lattice_hash",
    "lattice_values",
    "value_noise",
    "perlin_noise",
    "worley_noise",
    "value_lanes",
    "planar_corners",
    "planar_value_lanes",
    "chained_values",
    "perlin_lanes",
    "worley_lanes",
    "value_noise_scenes",
    "perlin_noise_scenes",
    "worley_noise_scenes",
    "scene_lattice_tables",
    "scene_rows",
    "default_noise_texture",
    "texture_noise",
    "texture_noise_reference",
    "texture_table",
    "fbm",
    "finest_period",
    "LLVMPIPE_FILTER_BITS",
]

_M32 = 0xFFFFFFFF


# --------------------------------------------------------------------------------------------
# Integer hash
# --------------------------------------------------------------------------------------------


def _mix32(h: Tensor) -> Tensor:
    """lowbias32 on int32 holding uint32 bits: int32 multiplies wrap mod 2**32 like uint32 ones;
    ``(h >> s) & mask`` is the logical shift (torch's ``>>`` on int32 is arithmetic)."""
    h = h ^ ((h >> 16) & 0xFFFF)
    h = h * 0x7FEB352D
    h = h ^ ((h >> 15) & 0x1FFFF)
    h = h * 0x1B873593
    return h ^ ((h >> 16) & 0xFFFF)


@functools.lru_cache(maxsize=4096)
def _seed32(seed: int) -> int:
    """A mixed 32-bit seed as a signed int32 value (so it fits an int32 tensor)."""
    h = (int(seed) * 0x9E3779B9 + 0x632BE5AB) & 0xFFFFFFFF
    h = _mix32(torch.tensor(h - (1 << 32) if h >= 1 << 31 else h, dtype=torch.int32))
    return int(h)


_SALTS = tuple(v - (1 << 32) if v >= 1 << 31 else v for v in (0x68E31DA4, 0xB5297A4D, 0x1B56C4E9))  # as int32 values


def hash3_lanes(x, y, z, seed: int):
    """`noise.hash3`'s 32 bits (int32 lanes holding uint32 bits) of integer cells (x, y, z) (int32
    lanes: values mod 2**32): lowbias32 chained over the mixed seed and each coordinate plus its
    salt. One source: `noise.hash3` takes its torch columns, the kernels their Dr.Jit arrays."""
    h = _seed32(seed)
    for c, salt in zip((x, y, z), _SALTS):
        h = _mix32(h ^ (c + salt))
    return h


def int32_bits(cells: Tensor) -> Tensor:
    """Integer cells ``[..., 3]`` (any integer dtype) mod 2**32, as int32 holding their uint32 bits."""
    c = cells.to(torch.int64) & _M32
    return (c - ((c >> 31) << 32)).to(torch.int32)


def _hash_u32(cells: Tensor, seed: int) -> Tensor:
    """uint32 hash (as int64) of integer cells ``[..., 3]`` and an integer seed -> ``[...]``:
    `hash3_lanes` (lowbias32 chained over the seed and the coordinates) on int32 columns."""
    c = int32_bits(cells)
    return hash3_lanes(c[..., 0], c[..., 1], c[..., 2], seed).to(torch.int64) & _M32


def hash3(cells: Tensor, seed: int, *, dtype: torch.dtype | None = None, kernel: bool = False) -> Tensor:
    """Hash integer lattice cells to uniform values in [0, 1).

    cells: ``[N, 3]`` integer tensor (any integer dtype; any values, taken mod 2**32 per axis).
    seed: any Python int (taken mod 2**32).
    dtype: float dtype of the result (default: ``torch.get_default_dtype()``).
    kernel: as one Dr.Jit kernel (float32 on the CPU: its ~30 integer ops in one pass, not 30
    passes over the cells; the same bits).
    Returns ``[N]`` in [0, 1): a 32-bit integer hash (lowbias32 mixing chained over the seed and
    the three coordinates) scaled by 2**-32 (float64) or its top 24 bits by 2**-24 (float32/16),
    so the value never rounds up to 1.
    """
    dtype = dtype or torch.get_default_dtype()
    if kernel and dtype == torch.float32 and cells.device.type == "cpu" and cells.numel():
        import drjit as dr
        from drjit.llvm import Int64, UInt32

        # the int64 cells read as they lie, each coordinate gathered in the kernel: no torch pass
        flat = Int64(cells.to(torch.int64).reshape(-1).contiguous().numpy())
        rows = dr.arange(UInt32, dr.width(flat) // 3) * 3
        return _unit_kernel([dr.gather(Int64, flat, rows + k) for k in range(3)], seed).reshape(cells.shape[:-1])
    return _u32_to_unit(_hash_u32(cells, seed), dtype)


def hash3_columns(x: Tensor, y: Tensor, z: Tensor, seed: int, *, dtype: torch.dtype | None = None,
                  kernel: bool = False) -> Tensor:
    """`hash3` of the cells whose coordinates are the integer columns x, y, z [n]: as
    ``hash3(torch.stack([x, y, z], 1), ...)`` (the eager path), without stacking them where it
    runs as a kernel (65 k rays' dither 0.44 -> 0.32 ms)."""
    dtype = dtype or torch.get_default_dtype()
    if kernel and dtype == torch.float32 and x.device.type == "cpu" and x.numel():
        from drjit.llvm import Int64

        return _unit_kernel([Int64(c.to(torch.int64).contiguous().numpy()) for c in (x, y, z)], seed)
    return hash3(torch.stack([x, y, z], dim=1), seed, dtype=dtype)


def _unit_kernel(cells: list, seed: int) -> Tensor:
    """`hash3`'s float32 values of cells given as three Int64 lanes, as one Dr.Jit kernel: each
    coordinate truncated to its low 32 bits (`int32_bits`' value, tested for any sign and size),
    hashed, its top 24 bits scaled -> [n] float32."""
    import drjit as dr
    from drjit.llvm import Int32

    unit = lanes.to_float((hash3_lanes(*(Int32(c) for c in cells), seed) >> 8) & 0xFFFFFF, 0.0) * 2.0**-24
    dr.eval(unit)
    return lanes.tensor_of(unit)


@functools.lru_cache(maxsize=64)
def _lattice_tables(seed: int, device: str) -> tuple[Tensor, Tensor]:
    """Perlin's permutation (doubled to 512 so chained lookups need no wrap) and 256 random
    triples in [0, 1), drawn from a generator seeded with `seed`."""
    g = torch.Generator().manual_seed(int(seed) % 2**63)
    perm = torch.randperm(256, generator=g)
    values = torch.rand(256, 3, generator=g, dtype=torch.float64)
    return torch.cat([perm, perm]).to(device), values.to(device)


def lattice_hash(cells: Tensor, seed: int) -> Tensor:
    """Perlin's classic lattice hash perm[perm[perm[x] + y] + z] of cells ``[..., 3]`` taken mod
    256 (period 256 per axis) -> ``[...]`` int64 in [0, 256).

    Three gathers from a 512-entry table instead of ~20 int64 mixing ops: the lattice noises call
    it 8 to 27 times per point. `hash3` stays the full-period hash for per-ray uses (dither)."""
    return _hash(cells, _lattice_tables(int(seed), str(cells.device))[0])


def _hash(cells: Tensor, perm: Tensor) -> Tensor:
    """`lattice_hash` of cells ``[..., 3]`` in a doubled permutation `perm` [512] (int64)."""
    c = cells & 255
    return take_rows(perm, take_rows(perm, take_rows(perm, c[..., 0]) + c[..., 1]) + c[..., 2])


def _cells(floors, offsets: Sequence[int], rows=None, period: int | None = None) -> list[list]:
    """Per axis, the lattice coordinates in [0, 256) (int32 lanes) of the cells `offsets` away
    along it from the cells whose lowest corners are `floors` (three float lanes, floor(p)), wrapped
    every `period` cells first (None: by the lattice's own 256 alone), each lane's `rows` (its block
    of stacked tables, None: 0) added along x: what `_lattice_chain` takes."""
    axes = []
    for a, lo in enumerate(floors):
        c = lanes.to_int32(lo)
        cells = [c + o if o else c for o in offsets]
        cells = [(x if period is None else lanes.remainder(x, period)) & 255 for x in cells]
        axes.append(cells if a or rows is None else [x + rows for x in cells])
    return axes


def _lattice_chain(perm, xs: list, ys: list, zs: list, last=None) -> list:
    """Perlin's chain perm[perm[perm[x] + y] + z] in a doubled permutation `perm` (int32, several
    scenes' stacked as `scene_lattice_tables` stacks them) for every cell of xs × ys × zs (`_cells`)
    -> their hashes (int32 lanes, x fastest: `_CORNERS`' order for the offsets (0, 1)), or, where
    `last` is a table composed with the permutation (`chained_values`), last[perm[perm[x] + y] + z]
    (a list of such tables: a list of their values per cell).

    The chain shares its prefixes: perm[x] once per x, perm[· + y] once per (x, y), so a cell's 8
    corners take 14 gathers instead of 24 and the 27 cells around a point 39 instead of 81; every
    index stays below 512 (the doubled table), within its scene's block. Bitwise `lattice_hash`."""
    px = [lanes.gather(perm, x) for x in xs]
    pxy = [lanes.gather(perm, h + y) for y in ys for h in px]
    rows = [h + z for z in zs for h in pxy]
    if isinstance(last, (list, tuple)):
        return [[lanes.gather(table, i) for table in last] for i in rows]
    return [lanes.gather(perm if last is None else last, i) for i in rows]


def chained_values(perm: Tensor, first: Tensor) -> Tensor:
    """Lattice values `first` [512·B] composed with the stacked permutation `perm` [512·B] (from
    `scene_lattice_tables`) -> first[perm] [512·B]: value noise reads a corner's value in the
    chain's last gather instead of a gather after it (8 of its 22 gathers a point; Dr.Jit's
    gathers are most of a value-noise kernel's time), Worley its feature points (27 of 120),
    bitwise the same values."""
    return take_rows(first, perm.long())


@functools.lru_cache(maxsize=16)
def scene_lattice_tables(seeds: tuple[int, ...], device: str) -> tuple[Tensor, tuple[Tensor, Tensor, Tensor]]:
    """`_lattice_tables` of several seeds stacked in blocks of 512 rows: block b holds seed b's
    doubled permutation plus 512·b (so a chained lookup never leaves its block, and the final
    hash is already a row of the block) and, in its first 256 rows, the three lattice-value
    columns -> (perm [512·B] int32, columns 3 × [512·B] float64). Value noise reads the first
    column, Worley's feature points all three, Perlin's gradients the hash alone; a point's block
    starts at its `scene_rows`."""
    perms, columns = [], [[], [], []]
    for b, seed in enumerate(seeds):
        perm, values = _lattice_tables(int(seed), device)
        perms.append(perm + 512 * b)
        for c in range(3):
            columns[c].append(torch.cat([values[:, c], values.new_zeros(256)]))
    return torch.cat(perms).to(torch.int32), tuple(torch.cat(col) for col in columns)


def scene_rows(scene: Tensor) -> Tensor:
    """Scene indices [N] -> the first rows [N] int32 of their blocks in `scene_lattice_tables`."""
    return scene.to(torch.int32) * 512


def value_noise_scenes(p: Tensor, rows: Tensor | None, seeds: Sequence[int]) -> Tensor:
    """`value_noise` of points p [N, 3], each with the seed of its scene (rows [N] from
    `scene_rows`, None: every point of the first; seeds: one per scene) -> [N]: one pass over every
    scene's points instead of one per scene, bitwise ``value_noise(p[i], seed=seeds[scene[i]])``."""
    perm, columns = _scene_tables(p, seeds)
    return value_lanes(*p.unbind(-1), perm, chained_values(perm, columns[0].to(p.dtype)), rows)


def perlin_noise_scenes(p: Tensor, rows: Tensor | None, seeds: Sequence[int], *, period: int | None = None) -> Tensor:
    """`perlin_noise` of points p [N, 3], each with the seed of its scene, as `value_noise_scenes`
    -> [N], bitwise ``perlin_noise(p[i], seed=seeds[scene[i]], period=period)``."""
    return perlin_lanes(*p.unbind(-1), _scene_tables(p, seeds)[0], rows, period=period)


def worley_noise_scenes(p: Tensor, rows: Tensor | None, seeds: Sequence[int], *, period: int | None = None) -> Tensor:
    """`worley_noise` of points p [N, 3], each with the seed of its scene, as `value_noise_scenes`
    -> [N], bitwise ``worley_noise(p[i], seed=seeds[scene[i]], period=period)``."""
    perm, columns = _scene_tables(p, seeds)
    return worley_lanes(*p.unbind(-1), perm, [chained_values(perm, c.to(p.dtype)) for c in columns], rows, period=period)


def _scene_tables(p: Tensor, seeds: Sequence[int]) -> tuple[Tensor, tuple[Tensor, Tensor, Tensor]]:
    """`scene_lattice_tables` of `seeds` on the device of points p [N, 3] (checked)."""
    _check_points(p)
    return scene_lattice_tables(tuple(int(s) for s in seeds), str(p.device))


def value_lanes(x, y, z, perm, chained, rows=None):
    """`value_noise` in lanes (`ops.lanes`: torch [N] or Dr.Jit) at points x, y, z (|p| < 2**31)
    from a doubled permutation `perm` (int32) and its lattice values in chain order `chained`
    (`chained_values`, the points' float type), each point's chain starting at its row `rows`
    (None: 0): what the Dr.Jit march traces (on the plane y = 0: `planar_value_lanes`)."""
    fl = [lanes.floor(c) for c in (x, y, z)]
    u = [fade(c - lo) for c, lo in zip((x, y, z), fl)]
    return _trilinear(_lattice_chain(perm, *_cells(fl, (0, 1), rows), last=chained), u)


@functools.lru_cache(maxsize=16)
def planar_corners(seed: int, dtype: torch.dtype) -> Tensor:
    """Value noise of `seed` on the plane y = 0 (a heightfield's) read ahead, cell by cell: each of
    the lattice's 256 × 256 cells' four y = 0 corner values, row 256·x + z of a table laid flat
    [4 · 65536] in `dtype` (x fastest, then z: `planar`'s order), the values `value_lanes`' chain
    reads (`_lattice_chain` into `chained_values`). A kernel reads a cell's corners in one packet
    gather (`lanes.gather_quad`) instead of the chain's eight dependent ones: a 256² terrain-clouds'
    trace kernel 13.6 -> 3.9 ms, the same bits. 1 MB a seed in float32."""
    perm, values = _lattice_tables(int(seed), "cpu")
    chained = chained_values(perm, torch.cat([values[:, 0], values.new_zeros(256)]))
    cells = torch.arange(256)
    v = chained[perm[perm[cells]][:, None] + cells[None, :]]  # [x, z]: chained[perm[perm[x]] + z]
    up = v.roll(-1, 0)  # x + 1 (the lattice wraps every 256 cells)
    return torch.stack([v, up, v.roll(-1, 1), up.roll(-1, 1)], -1).reshape(-1).to(dtype)


def planar_value_lanes(x, z, corners, rows):
    """`value_lanes` on the plane y = 0 at points x, z (lanes, `ops.lanes`) from `planar_corners`
    tables stacked (`corners`, laid flat; each lane's table from its row `rows`, int32 lanes:
    65536 · its block): bitwise `value_lanes` at (x, 0, z), from one row read a point, not eight."""
    fx, fz = lanes.floor(x), lanes.floor(z)
    cell = rows + (lanes.to_int32(fx) & 255) * 256 + (lanes.to_int32(fz) & 255)
    return planar(lanes.gather_quad(corners, cell), fade(x - fx), fade(z - fz))


def fade(g):
    """Value noise's smoothstep fade 3g² − 2g³ of a cell fraction `g` (lanes)."""
    return g * g * (3.0 - 2.0 * g)


def planar(vals: list, ux, uz):
    """`_trilinear` on the plane y = 0: its four y = 0 corners `vals` (x fastest, then z) blended
    by the fades `ux`, `uz` (lanes). There the fade along y is 0, and a lerp at weight 0 is exactly
    its first end (`lanes.lerp`, torch.lerp), so the y = 1 corners never change a bit: skipped."""
    return lanes.lerp(lanes.lerp(vals[0], vals[1], ux), lanes.lerp(vals[2], vals[3], ux), uz)


def lattice_values(cells: Tensor, seed: int, dtype: torch.dtype) -> Tensor:
    """Three uniform values in [0, 1) per lattice cell: ``[..., 3]`` -> ``[..., 3]``."""
    perm, values = _lattice_tables(int(seed), str(cells.device))
    return _values(cells, perm, values, dtype)


def _values(cells: Tensor, perm: Tensor, values: Tensor, dtype: torch.dtype) -> Tensor:
    """`lattice_values` of cells ``[..., 3]`` from `_lattice_tables`' `perm` [512] and `values` [256, 3]."""
    return take_rows(values, _hash(cells, perm)).to(dtype)


def _u32_to_unit(h: Tensor, dtype: torch.dtype) -> Tensor:
    if dtype == torch.float64:
        return h.to(dtype) * (2.0**-32)
    return (h >> 8).to(dtype) * (2.0**-24)


# --------------------------------------------------------------------------------------------
# Lattice noises
# --------------------------------------------------------------------------------------------

# the 8 corners of a unit cell, [8, 3] (x fastest)
_CORNERS = [(i & 1, (i >> 1) & 1, (i >> 2) & 1) for i in range(8)]


def _check_points(p: Tensor, name: str = "p") -> None:
    if p.ndim != 2 or p.shape[-1] != 3 or not p.is_floating_point():
        raise ValueError(f"{name}: got shape {tuple(p.shape)}, dtype {p.dtype}; float tensor [N, 3]")


def _trilinear(vals: list[Tensor], u: Tensor | Sequence[Tensor]) -> Tensor:
    """Blend 8 corner values (each ``[N]``, `_CORNERS` order) with weights ``u [N, 3]`` (or its
    three columns, each ``[N]``: lanes, `ops.lanes`)."""
    ux, uy, uz = u.unbind(-1) if isinstance(u, Tensor) else u
    x00 = lanes.lerp(vals[0], vals[1], ux)
    x10 = lanes.lerp(vals[2], vals[3], ux)
    x01 = lanes.lerp(vals[4], vals[5], ux)
    x11 = lanes.lerp(vals[6], vals[7], ux)
    return lanes.lerp(lanes.lerp(x00, x10, uy), lanes.lerp(x01, x11, uy), uz)


def value_noise(p: Tensor, *, seed: int = 0) -> Tensor:
    """Value noise: trilinear (smoothstep fade) blend of hashed lattice values.

    p: ``[N, 3]`` points. Returns ``[N]`` in [0, 1]; at integer points it equals
    ``lattice_values(p.long(), seed)[:, 0]``.
    """
    return value_noise_scenes(p, None, [seed])


def perlin_noise(p: Tensor, *, seed: int = 0, period: int | None = None) -> Tensor:
    """Gradient (Perlin) noise: hashed edge gradients, quintic fade 6t^5 - 15t^4 + 10t^3.

    p: ``[N, 3]`` points. Returns ``[N]``, 0 at integer points, within about [-1, 1] (the 12-edge
    gradient set bounds |value| by ~1.04 in theory; in practice it stays well inside [-1, 1]).
    period: the lattice repeats every `period` cells along each axis (tileable noise); None: 256.
    """
    return perlin_noise_scenes(p, None, [seed], period=period)


def perlin_lanes(x, y, z, perm, rows=None, *, period: int | None = None):
    """`perlin_noise` in lanes (`ops.lanes`: torch [N] or Dr.Jit) at points x, y, z (|p| < 2**31)
    from a doubled permutation `perm` (int32; several scenes' stacked as `scene_lattice_tables`
    stacks them), each lane's chain starting at its row `rows` (None: 0), the lattice repeating
    every `period` cells (None: 256): the 8 corners' edge gradients dotted with the point's offset
    from each corner, blended with the quintic fade. What the Dr.Jit march traces."""
    fl = [lanes.floor(c) for c in (x, y, z)]
    f = [c - lo for c, lo in zip((x, y, z), fl)]
    d = [(g, g - 1.0) for g in f]  # the offset from the corner below and from the one above, per axis
    dots = [_gradient_dot(h, *(d[a][corner[a]] for a in range(3)))
            for h, corner in zip(_lattice_chain(perm, *_cells(fl, (0, 1), rows, period)), _CORNERS)]
    return _trilinear(dots, [g * g * g * (g * (g * 6.0 - 15.0) + 10.0) for g in f])


def _gradient_dot(h, dx, dy, dz):
    """The dot product of Ken Perlin's edge gradient number h mod 12 with (dx, dy, dz), of hashes
    `h` (int32 lanes; ``& 255`` drops a stacked table's block offset 512·b) without a gather:
    gradient i of (1, 1, 0), (-1, 1, 0), (1, -1, 0), (-1, -1, 0), (1, 0, 1), (-1, 0, 1), (1, 0, -1),
    (-1, 0, -1), (0, 1, 1), (0, -1, 1), (0, 1, -1), (0, -1, -1) is ±u ± v with u = dx for i < 8
    else dy, v = dy for i < 4 else dz, u negated where bit 0 of i is set, v where bit 1 is. Both
    terms are exact, so the sum rounds once, as the three products' sum does."""
    i = (h & 255) % 12
    u = lanes.where(i < 8, dx, dy)
    v = lanes.where(i < 4, dy, dz)
    return lanes.where((i & 1) == 0, u, -u) + lanes.where((i & 2) == 0, v, -v)


def worley_noise(p: Tensor, *, seed: int = 0, period: int | None = None) -> Tensor:
    """Worley (cellular) noise F1: distance to the nearest feature point, clamped to [0, 1].

    One feature point per unit cell at ``cell + lattice_values(cell, seed)``; the 27 cells around
    the point's cell are searched.
    p: ``[N, 3]`` points. Returns ``[N]`` in [0, 1].
    period: feature points repeat every `period` cells along each axis (tileable noise).
    """
    return worley_noise_scenes(p, None, [seed], period=period)


# the 27 cells around a point's cell, as `_lattice_chain` orders them (x fastest)
_NEIGHBOURS = [(dx, dy, dz) for dz in (-1, 0, 1) for dy in (-1, 0, 1) for dx in (-1, 0, 1)]


def worley_lanes(x, y, z, perm, values, rows=None, *, period: int | None = None):
    """`worley_noise` in lanes (`ops.lanes`) at points x, y, z (|p| < 2**31): the distance to the
    nearest of the feature points of the 27 cells around, clamped to [0, 1]. `perm`: doubled
    permutations (int32; several scenes' stacked as `scene_lattice_tables` stacks them), `values`:
    the feature points' three offset columns in chain order (`chained_values`, the points' float
    type), `rows`:
    each lane's block (None: 0), `period`: the feature points repeat every `period` cells (None: 256)."""
    fl = [lanes.floor(c) for c in (x, y, z)]
    f = [c - lo for c, lo in zip((x, y, z), fl)]
    best = math.inf
    for point, off in zip(_lattice_chain(perm, *_cells(fl, (-1, 0, 1), rows, period), last=values), _NEIGHBOURS):
        d = [(off[a] + point[a]) - f[a] for a in range(3)]
        best = lanes.minimum(best, lanes.dot3(d, d))
    return lanes.clamp(lanes.sqrt(best), 0.0, 1.0)


# --------------------------------------------------------------------------------------------
# Texture noise (the seed template's noise(), iChannel0 = 256x256 RGBA8 noise texture)
# --------------------------------------------------------------------------------------------

#: Sub-texel bits of Mesa llvmpipe's RGBA8 bilinear filter (measured; see `texture_noise`).
LLVMPIPE_FILTER_BITS = 8

_TEX = 256
_G_SHIFT = (37, 239)  # G(x, y) = R(x - 37, y - 239)


def default_noise_texture(seed: int = 0) -> Tensor:
    """The 256x256 RGBA8 noise texture for `texture_noise` (ShaderToy's "Gray Noise Small" role).

    Returns a ``torch.uint8`` tensor ``(256, 256, 4)`` indexed ``[y, x, channel]`` with row ``y``
    the texture's v axis as OpenGL uploads it (row 0 is v≈0). R, B and A are uniform random bytes
    from a ``torch.Generator`` seeded with `seed`; ``G[y, x] = R[(y - 239) % 256, (x - 37) % 256]``,
    which makes the template's ``uv = p.xy + (37, 239) * p.z`` / ``.yx`` / ``mix(.., f.z)`` lookup a
    continuous 3D noise (the value at z = k from below equals the value from above).
    """
    g = torch.Generator(device="cpu").manual_seed(int(seed))
    tex = torch.randint(0, 256, (_TEX, _TEX, 4), generator=g, dtype=torch.uint8)
    tex[..., 1] = torch.roll(tex[..., 0], shifts=(_G_SHIFT[1], _G_SHIFT[0]), dims=(0, 1))
    return tex


_PACKED: dict[int, tuple] = {}  # id(texture) -> (weakref, (version, device), table)


def texture_table(texture, device: torch.device | str = "cpu") -> Tensor:
    """``(256, 256, 4)`` uint8 -> ``[65536, 2]`` float64 table of (G, R) in 0..255.

    Cached per live texture tensor (weak reference; invalidated by in-place edits via the version counter).
    """
    tex = torch.as_tensor(texture)
    if tuple(tex.shape) != (_TEX, _TEX, 4) or tex.dtype != torch.uint8:
        raise ValueError(
            f"texture: got shape {tuple(tex.shape)}, dtype {tex.dtype}; "
            "torch.uint8 (256, 256, 4) indexed [y, x, channel]"
        )
    key = (tex._version, str(device))
    if isinstance(texture, Tensor):
        hit = _PACKED.get(id(texture))
        if hit is not None and hit[0]() is texture and hit[1] == key:
            return hit[2]
    flat = tex.reshape(-1, 4).to(device)
    table = flat[:, [1, 0]].to(torch.float64)
    if isinstance(texture, Tensor):
        for k in [k for k, v in _PACKED.items() if v[0]() is None]:  # drop dead textures
            del _PACKED[k]
        _PACKED[id(texture)] = (weakref.ref(texture), key, table)
    return table


def texture_noise(p: Tensor, texture: Tensor, *, filter_bits: int | None = LLVMPIPE_FILTER_BITS) -> Tensor:
    """The seed template's texture value noise, without its final ``* 2 - 1``.

    p: ``[N, 3]`` points; texture: ``torch.uint8 (256, 256, 4)`` indexed ``[y, x, channel]``
    (e.g. `default_noise_texture`). Returns ``[N]`` in [0, 1] in ``p``'s dtype. The GLSL::

        vec3 p = floor(x); vec3 f = fract(x); f = f*f*(3.0-2.0*f);
        vec2 uv = (p.xy + vec2(37.0,239.0)*p.z) + f.xy;
        vec2 rg = textureLod(iChannel0, (uv + 0.5)/256.0, 0.0).yx;
        return mix(rg.x, rg.y, f.z);

    with GL_LINEAR filtering and GL_REPEAT wrap, op for op in ``p``'s dtype (float32 gives the
    shader's rounding; ``mix(a, b, t)`` is ``a + t * (b - a)`` as llvmpipe evaluates it).

    filter_bits: how the bilinear filter is evaluated.

    * ``8`` (default, `LLVMPIPE_FILTER_BITS`) — Mesa llvmpipe's RGBA8 path (gallivm AoS sampler),
      measured on Mesa 22.3.6 / LLVM 15 to match bit for bit: the normalised coordinate is scaled
      to ``256 * 2**8`` fixed point and rounded to nearest-even (``s = round((uv + 0.5) * 256)``),
      then ``s -= 128``; texel index ``s >> 8`` (wrapped mod 256), weight ``w = s & 255``.
      Filtering stays in 8-bit integers: each lerp is ``a + ((w * (b - a) + 128) >> 8)``,
      along x first (two rows), then along y. The 8-bit result ``k`` becomes ``k * float(1/255)``.
      Consequently each texture sample is a multiple of 1/255 (not the exact bilinear value:
      differences up to ~0.005, i.e. 1.3/255). The x86 float->int32 overflow (|uv| >= 2**23,
      result 0x80000000) is reproduced too.
    * other ints ``b`` (1..15) — the same fixed-point scheme with ``b`` sub-texel bits.
    * ``None`` — ideal GL_LINEAR: exact float bilinear weights ``fract(uv)`` on texels / 255.
    """
    _check_points(p)
    table = texture_table(texture, p.device)
    if filter_bits is None:
        return texture_noise_reference(p, table, filter_bits=None)
    return texture_noise_coords(*p.unbind(1), packed_table(table), filter_bits=filter_bits)


def texture_noise_reference(p: Tensor, table: Tensor, *, filter_bits: int | None = LLVMPIPE_FILTER_BITS) -> Tensor:
    """`texture_noise` on a prepared `texture_table` ``[65536, 2]``, the slow, obvious form: the
    fixed-point filter's integer steps as exact float64 arithmetic (`texture_noise_coords`, what
    renders, is bitwise it in integers; tests/test_noise.py), and the ideal filter
    (``filter_bits=None``)."""
    dtype, dev = p.dtype, p.device
    fl = torch.floor(p)
    f = p - fl
    f = f * f * (3.0 - 2.0 * f)
    k37_239 = torch.tensor([37.0, 239.0], dtype=dtype, device=dev)
    uv = (fl[:, :2] + k37_239 * fl[:, 2:3]) + f[:, :2]  # [N, 2]
    if filter_bits is None:
        fu = torch.floor(uv)
        w = uv - fu  # [N, 2]
        i0 = fu.to(torch.int64)
        x0, y0 = i0[:, 0] & 255, i0[:, 1] & 255
        x1, y1 = (x0 + 1) & 255, (y0 + 1) & 255
        def fetch(y: Tensor, x: Tensor) -> tuple[Tensor, Tensor]:
            v = table[y * 256 + x].to(dtype) / 255.0
            return v[:, 0], v[:, 1]

        (g00, r00), (g01, r01) = fetch(y0, x0), fetch(y0, x1)
        (g10, r10), (g11, r11) = fetch(y1, x0), fetch(y1, x1)
        wx, wy = w[:, 0], w[:, 1]
        g = torch.lerp(torch.lerp(g00, g01, wx), torch.lerp(g10, g11, wx), wy)
        r = torch.lerp(torch.lerp(r00, r01, wx), torch.lerp(r10, r11, wx), wy)
    else:
        bits = int(filter_bits)
        if not 1 <= bits <= 15:
            raise ValueError(f"filter_bits: got {filter_bits!r}; None or an int in 1..15")
        one, half = float(1 << bits), float(1 << (bits - 1))
        # (uv + 0.5) / 256 * (256 << bits): the /256 and *2**k are exact in binary floating point
        s = torch.round((uv + 0.5) * one)
        bad = ~(s.abs() < 2.0**31)  # x86 cvt overflow / NaN -> 0x80000000
        # the integer steps in float64: exact for these magnitudes
        s = torch.where(bad, torch.full_like(s, -(2.0**31)), s).to(torch.float64)
        s = torch.remainder(s - half + 2.0**31, 2.0**32) - 2.0**31  # int32 wrap of the -0.5 texel shift
        i0 = torch.floor(s / one)
        w = s - i0 * one  # [N, 2] weights in [0, 2**bits)
        x0, y0 = torch.remainder(i0[:, 0], 256.0), torch.remainder(i0[:, 1], 256.0)
        x1, y1 = torch.remainder(x0 + 1.0, 256.0), torch.remainder(y0 + 1.0, 256.0)
        wx, wy = w[:, 0:1], w[:, 1:2]
        at = lambda y, x: take_rows(table, (y * 256.0 + x).long())  # noqa: E731  [N, 2] (G, R)

        def lerp(a: Tensor, b: Tensor, wt: Tensor) -> Tensor:  # a + ((w (b − a) + half) >> bits)
            return torch.floor((a * (one - wt) + b * wt + half) / one)

        v = lerp(lerp(at(y0, x0), at(y0, x1), wx), lerp(at(y1, x0), at(y1, x1), wx), wy)
        inv255 = torch.tensor(1.0 / 255.0, dtype=dtype, device=dev)  # unorm8 -> float, as llvmpipe
        g = v[:, 0].to(dtype) * inv255
        r = v[:, 1].to(dtype) * inv255
    fz = f[:, 2]
    return g + fz * (r - g)


def packed_table(table: Tensor) -> Tensor:
    """A `texture_table` ``[M, 2]`` of (G, R) as int32 ``[M]``, G + 256·R: one gather per texel."""
    t = table.to(torch.int32)
    return t[:, 0] + t[:, 1] * 256


def texture_index_dtype(dtype: torch.dtype) -> torch.dtype:
    """The integer type of `texture_noise_coords`' steps and table rows for points of `dtype`."""
    return torch.int32 if dtype == torch.float32 else torch.int64


def texture_rows(scene: Tensor, dtype: torch.dtype) -> Tensor:
    """Scene indices [N] -> each one's first row [N] in its batch's stacked texture tables (a
    `texture_table` of 256 × 256 rows per scene, `torch.cat`), the `base` of `texture_noise_coords`
    for points of `dtype`."""
    return scene.to(texture_index_dtype(dtype)) * (256 * 256)


def texture_noise_coords(x, y, z, packed, base=None, *, filter_bits: int = LLVMPIPE_FILTER_BITS):
    """`texture_noise` with a fixed-point filter for points given as their coordinates (each
    ``[N]``) and a `packed_table`, its integer steps in integers (int32 for float32 points, int64
    for float64): bitwise `texture_noise_reference`'s float64 steps, ~4× faster eager. `base` ``[N]``: rows
    in stacked tables. Lanes (`ops.lanes`): with Dr.Jit arrays (float32, int32 `packed` and
    `base`) it is what the template's Dr.Jit march traces (`fields.clouds.clouds_density`),
    bitwise these values."""
    bits = int(filter_bits)
    if not 1 <= bits <= 15:
        raise ValueError(f"filter_bits: got {filter_bits!r}; an int in 1..15")
    wide = isinstance(x, Tensor) and texture_index_dtype(x.dtype) == torch.int64
    one, half = 1 << bits, 1 << (bits - 1)
    fx, fy, fz = lanes.floor(x), lanes.floor(y), lanes.floor(z)
    wx_, wy_, wz = x - fx, y - fy, z - fz
    wx_, wy_, wz = wx_ * wx_ * (3.0 - 2.0 * wx_), wy_ * wy_ * (3.0 - 2.0 * wy_), wz * wz * (3.0 - 2.0 * wz)
    u = (fx + 37.0 * fz) + wx_
    v = (fy + 239.0 * fz) + wy_

    def texel(c):  # (i0 & 255, i1 & 255, weight) of one axis
        s = lanes.round((c + 0.5) * float(one))
        bad = ~(lanes.abs(s) < 2.0**31)  # x86 cvt overflow / NaN -> 0x80000000, then the int32 wrap of −half
        if wide:
            si = torch.where(bad, -(2.0**31), s).to(torch.int64) - half
            shifted = torch.where(si < -(2**31), si + 2**32, si)
        else:  # |s| < 2**31 in float32 is at most 2**31 − 128: s − half cannot wrap
            shifted = lanes.where(bad, lanes.int_like(2**31 - half, s), lanes.to_int32(lanes.where(bad, 0.0, s)) - half)
        i0 = shifted >> bits
        return i0 & 255, (i0 + 1) & 255, shifted & (one - 1)

    x0, x1, wx = texel(u)
    y0, y1, wy = texel(v)
    row0, row1 = y0 * 256, y1 * 256
    if base is not None:
        row0, row1 = row0 + base, row1 + base
    at = lambda row, col: lanes.gather(packed, row + col)  # noqa: E731

    def lerp(a, b, w):  # a + ((w (b − a) + half) >> bits), both channels
        return ((a & 255) * (one - w) + (b & 255) * w + half) >> bits, ((a >> 8) * (one - w) + (b >> 8) * w + half) >> bits

    (g0, r0), (g1, r1) = lerp(at(row0, x0), at(row0, x1), wx), lerp(at(row1, x0), at(row1, x1), wx)
    g = lanes.to_float((g0 * (one - wy) + g1 * wy + half) >> bits, x) * (1.0 / 255.0)
    r = lanes.to_float((r0 * (one - wy) + r1 * wy + half) >> bits, x) * (1.0 / 255.0)
    return g + wz * (r - g)




# --------------------------------------------------------------------------------------------
# fBm
# --------------------------------------------------------------------------------------------


def _mesa_folded_scales(steps: Sequence[float], dtype: torch.dtype, device) -> list[Tensor]:
    """Constants ``C_k`` with ``q_k = p * C_k`` as Mesa's NIR folds ``q *= l_0; q *= l_1; ...``.

    Model (fitted to Mesa 22.3.6 llvmpipe, bit-exact for chains of 4 and 6 multipliers):
    nir_opt_algebraic rewrites ``fmul(fmul(a, #b), #c) -> fmul(a, fmul(b, c))``, visiting the
    instructions last to first, where ``#`` only matches an already folded constant; the new
    ``fmul(b, c)`` becomes a constant at the next constant-folding pass; passes repeat until
    nothing changes. For four multipliers: ``q_2 = p*(l0*l1)``, ``q_3 = p*(l0*(l1*l2))``,
    ``q_4 = p*((l0*l1)*(l2*l3))`` — not the sequential ``((p*l0)*l1)...`` of the source.
    steps: ``[l_0, ..., l_{K-1}]``. Returns ``[C_1, ..., C_K]`` as 0-dim tensors in `dtype`.
    """
    # node k (1..K): [source node index (0 = p), constant tree, constant tree is folded]
    nodes: list[list] = [[None, None, True]] + [[k - 1, float(l), True] for k, l in enumerate(steps, 1)]
    changed = True
    while changed:
        changed = False
        for k in range(len(nodes) - 1, 0, -1):  # last instruction first
            src, const, folded = nodes[k]
            if folded and src >= 1:
                s_src, s_const, s_folded = nodes[src]
                if s_folded:
                    nodes[k] = [s_src, (s_const, const), False]
                    changed = True
        for node in nodes:
            node[2] = True

    def value(tree) -> Tensor:
        if isinstance(tree, tuple):
            return value(tree[0]) * value(tree[1])
        return torch.tensor(tree, dtype=dtype, device=device)

    out = []
    for k in range(1, len(nodes)):  # resolve chains q_k = q_src * C: C_k = C_src * C (src < k)
        src, const, _ = nodes[k]
        c = value(const)
        out.append(c if src == 0 else out[src - 1] * c)
    return out


# the seeds' fbm multipliers, cycled: q *= 2.02; q *= 2.03; q *= 2.01; q *= 2.02; ...
LACUNARITY = (2.02, 2.03, 2.01, 2.02)


def octave_steps(octaves: int, lacunarity: float | Sequence[float] = LACUNARITY) -> list[float]:
    """The multipliers ``[l_0, ..., l_{octaves-2}]`` between `fbm`'s octaves (a sequence cycles)."""
    lac = [float(lacunarity)] if isinstance(lacunarity, (int, float)) else [float(x) for x in lacunarity]
    return [lac[k % len(lac)] for k in range(octaves - 1)]


def folded_scales(octaves: int, lacunarity: float | Sequence[float] = LACUNARITY, *, dtype: torch.dtype,
                  device) -> list[Tensor]:
    """`fbm`'s octave scales ``[C_1, ..., C_{octaves-1}]`` (``q_k = p * C_k``) as Mesa folds them,
    0-dim tensors in `dtype`: what a kernel that evaluates the octaves itself multiplies by."""
    return _mesa_folded_scales(octave_steps(octaves, lacunarity), dtype, device)


def finest_period(octaves: int, lacunarity: float | Sequence[float] = LACUNARITY) -> float:
    """The lattice period of `fbm`'s last octave, in units of its input: the scale below which
    nothing in the sum varies (the noise bases have period 1 on their lattice)."""
    scale = 1.0
    for step in octave_steps(octaves, lacunarity):
        scale *= step
    return 1.0 / scale


def _check_fbm(p: Tensor, *, octaves: int, lacunarity: float | Sequence[float], fold: str,
               lod: Tensor | None) -> Tensor | None:
    """`fbm`'s arguments checked (ValueError); -> `lod` as an [N] tensor (a scalar broadcast), or None."""
    _check_points(p)
    if octaves < 1:
        raise ValueError(f"octaves: got {octaves!r}; an integer >= 1")
    if not isinstance(lacunarity, (int, float)) and len(lacunarity) == 0:
        raise ValueError(f"lacunarity: got {lacunarity!r}; a number or a non-empty sequence")
    if fold not in ("mesa", "sequential"):
        raise ValueError(f"fold: got {fold!r}; 'mesa' or 'sequential'")
    if lod is not None:
        lod = torch.as_tensor(lod, device=p.device)
        if lod.ndim == 0:
            lod = lod.expand(p.shape[:1])
        if lod.shape != p.shape[:1]:
            raise ValueError(f"lod: got shape {tuple(lod.shape)}; [N] with N = {p.shape[0]}")
    return lod


def fbm(
    p: Tensor,
    noise: Callable[[Tensor], Tensor],
    *,
    octaves: int = 5,
    lacunarity: float | Sequence[float] = LACUNARITY,
    gain: float = 0.5,
    lod: Tensor | None = None,
    fold: str = "mesa",
    rows: Tensor | None = None,
) -> Tensor:
    """Fractal sum of `noise` octaves, in the seeds' float order.

    p: ``[N, 3]`` points; noise: ``[M, 3] -> [M]`` (e.g. ``lambda q: texture_noise(q, tex)*2-1``).
    Octave ``k`` has weight ``0.5 * gain**k`` (0.5, 0.25, 0.125, ... for gain 0.5) and is evaluated
    at ``q_k``, the point after ``k`` lacunarity multiplications (``lacunarity[i % len]`` after
    octave ``i``; a scalar lacunarity is used for every octave): the GLSL
    ``f = 0.5*n(q); q *= 2.02; f += 0.25*n(q); q *= 2.03; ...``. The sum is accumulated left to
    right (``f = f + w*n``; the weights are powers of two, so ``w*n`` is exact).

    rows: optional per-point data ``[N, ...]`` handed to the noise beside the points, compacted with
        them under `lod`: ``noise(q, rows)`` (e.g. each point's scene block, `value_noise_scenes`).

    fold: how ``q_k`` is rounded (it matters: one ulp of q moves texture noise by up to ~1e-2).

    * ``"mesa"`` (default): ``q_k = p * C_k`` with the constants as Mesa's shader compiler folds
      the GLSL multiply chain (see `_mesa_folded_scales`; for the default lacunarity
      ``C = 2.02, 2.02*2.03, 2.02*(2.03*2.01), (2.02*2.03)*(2.01*2.02)``, each product rounded
      in ``p``'s dtype). Measured bit-exact against llvmpipe for 5 and 7 octaves; the sequential
      product differs by an ulp of q in ~30-100% of points from the third octave on.
    * ``"sequential"``: ``q = q * l`` after every octave, as the source is written.

    lod: optional ``[N]`` (or scalar) level of detail (the template's ``int lod``): octave 0 is
        always added, octave ``k >= 1`` only where ``lod >= k + 1``. Each octave is evaluated only
        on the points that need it (active points are compacted, so low LOD saves evaluations).
    Returns ``[N]`` in ``p``'s dtype.
    """
    lod = _check_fbm(p, octaves=octaves, lacunarity=lacunarity, fold=fold, lod=lod)
    dtype, dev = p.dtype, p.device
    steps = octave_steps(octaves, lacunarity)
    scales = _mesa_folded_scales(steps, dtype, dev) if fold == "mesa" else None
    f = (noise(p) if rows is None else noise(p, rows)) * 0.5
    q, pa, ra = p, p, rows  # q: sequential point; pa, ra: the active original points and their rows
    idx: Tensor | None = None  # indices of the active points (None: all of them)
    for k in range(1, octaves):
        if lod is not None:
            keep = (lod if idx is None else lod[idx]) >= k + 1
            if not bool(keep.all()):
                idx = keep.nonzero().squeeze(1) if idx is None else idx[keep]
                pa, q = pa[keep], q[keep]
                ra = None if ra is None else ra[keep]
            if pa.shape[0] == 0:
                break
        q = pa * scales[k - 1] if scales is not None else q * torch.tensor(steps[k - 1], dtype=dtype, device=dev)
        term = (noise(q) if ra is None else noise(q, ra)) * (0.5 * gain**k)
        f = f + term if idx is None else f.index_add(0, idx, term)
    return f
