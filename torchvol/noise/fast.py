"""Value-noise fBm with an arithmetic integer hash (``density.fbm.hash = "arithmetic"``): a twin
field of ``noise.fbm`` over ``noise.value_noise`` without its gathers.

`noise.value_noise` hashes lattice corners with Perlin's permutation table: three dependent
gathers per corner, which do not vectorise. Here each corner's value comes from int32
multiplies, xors and shifts only (``h = mix32(x·P1 ^ y·P2 ^ z·P3 ^ seed)``, lowbias32 finaliser,
int32 arithmetic wrapping mod 2**32), in lanes (`ops.lanes`): the Dr.Jit march traces the whole
fBm (`fbm_sum`, `fbm_field`) into its kernel as vector arithmetic.

`fbm_value_hashed` is the eager form: ``noise.fbm`` (the seeds' float order, Mesa's folded octave
scales, LOD compaction) over `value_noise_hashed`; `fbm_sum` evaluates every octave and masks the
ones LOD drops instead of compacting, which adds exact zeros. The lattice values are a different
random field than the table's, with the same distribution (uniform 24-bit values in [0, 1)), so
images change where a scene switches hash; the statistics do not (tests/test_fastnoise.py).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from ..ops import lanes
from . import lattice as noise
from .lattice import _mix32, _seed32

__all__ = ["hash32", "hash_cells", "hash_pair", "value_noise_hashed", "fbm_value_hashed", "fbm_sum", "fbm_field", "mixed_seeds"]

# odd multipliers below 2**31 (xxHash's primes and murmur3's c2): Python ints that stay int32 in torch
_P = (0x1B873593, 0x27D4EB2F, 0x165667B1)


def hash32(x, y, z, seed):
    """The 32-bit hash (int32 bits) of integer cells (x, y, z), each int32 lanes or ints (values
    taken mod 2**32), and a mixed seed (`_seed32`): lanes (`ops.lanes`)."""
    return _mix32((x * _P[0]) ^ (y * _P[1]) ^ (z * _P[2]) ^ seed)


def hash_pair(a, b, seed):
    """The 32-bit hash (int32 bits) of an integer pair, two chained lowbias32 rounds (the first of
    `a` and the seed, the second of that and `b`): counter-based random numbers, where one round
    over a product sum left consecutive counters correlated. Lanes (`ops.lanes`)."""
    return _mix32(_mix32(a ^ seed) ^ b)


def hash_cells(x: Tensor, y: Tensor, z: Tensor, seed: Tensor | int) -> Tensor:
    """Uniform values in [0, 1) of integer lattice cells (x, y, z), each ``[N]`` int32 (values
    taken mod 2**32), and a mixed seed (`_seed32`; int or 0-dim int32 tensor) -> ``[N]`` int32 in
    [0, 2**24): the hash's top 24 bits."""
    return (hash32(x, y, z, seed) >> 8) & 0xFFFFFF


def _value(p: Sequence[Tensor | None], seed: Tensor | int) -> Tensor:
    """Value noise of points given as their three coordinates (each ``[N]``) with a mixed seed
    -> ``[N]`` in [0, 1) (`value_noise_hashed`); lanes (`ops.lanes`). y None: on the plane y = 0,
    bitwise the value there from its four y = 0 corners (`noise.planar`)."""
    axes = [c for c in p if c is not None]
    fl = [lanes.floor(c) for c in axes]
    u = [noise.fade(c - f) for c, f in zip(axes, fl)]
    x0, *_, z0 = (lanes.to_int32(f) for f in fl)
    # hash_cells' products per axis once, not per corner (xor is associative: the same bits); on
    # the plane the y = 0 cells' xor with 0 · P1 leaves them as they are
    hx = [x * _P[0] for x in (x0, x0 + 1)]
    hxy = hx if p[1] is None else [h ^ (y * _P[1]) for y in (lanes.to_int32(fl[1]), lanes.to_int32(fl[1]) + 1) for h in hx]
    vals = [lanes.to_float((_mix32(h ^ hz) >> 8) & 0xFFFFFF, p[0]) * 2.0**-24
            for hz in ((z0 * _P[2]) ^ seed, ((z0 + 1) * _P[2]) ^ seed) for h in hxy]  # noise._CORNERS order
    return noise.planar(vals, *u) if p[1] is None else noise._trilinear(vals, u)


def value_noise_hashed(p: Tensor, *, seed: int = 0) -> Tensor:
    """Value noise with the arithmetic hash: `noise.value_noise`'s signature and fade, lattice values
    from `hash_cells`. p: ``[N, 3]`` float points with |p| < 2**31. Returns ``[N]`` in [0, 1)."""
    noise._check_points(p)
    return _value(p.unbind(-1), _seed32(seed))


def fbm_sum(basis, x, y, z, scales, lod, octaves: int, gain: float):
    """Every octave of `noise.fbm` in its float order, LOD as a mask, in lanes (`ops.lanes`):
    `basis(x, y, z)` the noise (this module's arithmetic hash, or `noise.value_lanes` over the
    tables); x, y, z each ``[N]``; scales ``[octaves - 1]`` or a list; lod ``[N]`` octaves kept, or None.
    What the Dr.Jit march's densities trace."""
    f = basis(x, y, z) * 0.5
    for k in range(1, octaves):
        s = scales[k - 1]
        term = basis(x * s, y * s, z * s) * (0.5 * gain**k)
        f = f + (term if lod is None else lanes.where(lod >= k + 1, term, 0.0))
    return f


def hashed(seed, *, plane: bool = False):
    """The arithmetic-hash value noise with mixed seed `seed` (per point or one) as `fbm_sum`'s
    basis; `plane`: on the plane y = 0 (its y argument, 0, unread: `_value`)."""
    return (lambda x, y, z: _value((x, None, z), seed)) if plane else (lambda x, y, z: _value((x, y, z), seed))


def fbm_field(x, y, z, basis, scales, count, q, *, octaves: int, gain: float = 0.5):
    """The fbm field's signed density, lanes (`ops.lanes`: torch [N] or Dr.Jit): `puff` of
    `fbm_sum` over `basis` at frequency·(p − shift) + offset. x, y, z: the points'
    coordinates; basis: `fbm_sum`'s (`hashed(seed)`, seeds from `mixed_seeds`); scales: the octave
    scales (`noise.folded_scales`), a list or [octaves − 1]; count: octaves kept per point or None;
    `q`: the field's per-point parameters, attributes frequency, bias, amplitude, radial and
    shift, offset, center (three lanes each). What the Dr.Jit march runs (`fields.fbm.fbm_density`)."""
    u = [q.frequency * (c - q.shift[i]) + q.offset[i] for i, c in enumerate((x, y, z))]
    f = fbm_sum(basis, *u, scales, count, octaves, gain)
    return puff(f, x, y, z, q)


def puff(f, x, y, z, q):
    """bias + amplitude · f − radial · |p − center|: the fbm `f` made a puff around its centre, in
    lanes (`ops.lanes`): x, y, z the points' coordinates, `q` the per-point bias, amplitude, radial
    and center (three lanes)."""
    c = q.center
    return q.bias + q.amplitude * f - q.radial * lanes.length3(x - c[0], y - c[1], z - c[2])


def fbm_value_hashed(
    p: Tensor,
    *,
    seed: int = 0,
    octaves: int = 5,
    lacunarity: float | Sequence[float] = noise.LACUNARITY,
    gain: float = 0.5,
    lod: Tensor | None = None,
) -> Tensor:
    """``noise.fbm(p, lambda q: value_noise_hashed(q, seed=seed), ...)`` (fold "mesa"). p:
    ``[N, 3]`` points; lod: optional ``[N]`` (or scalar) as in `noise.fbm`. Returns ``[N]``."""
    return noise.fbm(p, lambda q: value_noise_hashed(q, seed=seed), octaves=octaves, lacunarity=lacunarity, gain=gain,
                     lod=lod)


def mixed_seeds(seeds: Sequence[int], device) -> Tensor:
    """Scene seeds as the hash takes them: ``[B]`` int32 of `_seed32` values."""
    return torch.tensor([_seed32(int(x)) for x in seeds], dtype=torch.int32, device=device)
