"""Tileable 3D noise textures: the production clouds' (Horizon Zero Dawn style) Perlin-Worley base
shape and Worley detail noise, built once per (seed, size) and sampled trilinearly with wrap-around.

A texture of size N is a (N, N, N) float32 tensor indexed [k, j, i] (i along x, j along y, k along
z); node (i, j, k) holds the generating noise at ``(i, j, k) / N`` in *texture coordinates*, where
the texture repeats with period 1. Each octave's noise has an integer number of lattice cells per
period (`perlin_noise` / `worley_noise` with ``period=``), so the texture tiles seamlessly.
Building costs one noise evaluation per node and octave (a 64³ base: ~0.3 M nodes); sampling
costs 8 gathers and 7 lerps per point, whatever the octaves (`tiled_lanes`: eager and the Dr.Jit
kernels alike).
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor

from ..ops import lanes
from . import lattice as noise
from .lattice import _trilinear

__all__ = ["BASE_SIZE", "DETAIL_SIZE", "perlin_worley", "worley_fbm", "base_texture", "detail_texture",
           "texture_nodes", "sample_tiled", "tiled_lanes"]

BASE_SIZE = 64  # nodes per period of the base shape texture
DETAIL_SIZE = 32  # nodes per period of the detail texture
BASE_FREQUENCIES = (4, 8, 16)  # lattice cells per period of each octave
DETAIL_FREQUENCIES = (2, 4, 8)
_WEIGHTS = (0.625, 0.25, 0.125)  # octave weights (sum 1: the fbm stays in [0, 1])


def worley_fbm(uvw: Tensor, *, seed: int, frequencies: tuple[int, ...]) -> Tensor:
    """Inverted Worley F1 fBm, 1 − F1 summed over octaves (`_WEIGHTS`), periodic with period 1.
    `uvw`: [n, 3] texture coordinates -> [n] in [0, 1] (1 on feature points: billowy cells)."""
    out = torch.zeros_like(uvw[:, 0])
    for k, (freq, w) in enumerate(zip(frequencies, _WEIGHTS)):
        out = out + w * (1.0 - noise.worley_noise(uvw * freq, seed=seed + 101 * k, period=freq))
    return out


def perlin_worley(uvw: Tensor, *, seed: int, frequencies: tuple[int, ...] = BASE_FREQUENCIES) -> Tensor:
    """The Perlin-Worley base shape, periodic with period 1: Perlin fBm remapped from
    [worley − 1, 1] to [0, 1] (HZD: Worley's billows cut into the Perlin's connected shapes).
    `uvw`: [n, 3] texture coordinates -> [n] (roughly [0, 1]; `base_texture` normalises it)."""
    perlin = torch.zeros_like(uvw[:, 0])
    for k, (freq, w) in enumerate(zip(frequencies, _WEIGHTS)):
        perlin = perlin + w * noise.perlin_noise(uvw * freq, seed=seed + 7 * k, period=freq)
    perlin = (0.5 + perlin).clamp(0.0, 1.0)  # Perlin fBm stays within about ±0.5
    worley = worley_fbm(uvw, seed=seed + 1, frequencies=frequencies)
    return (perlin - (worley - 1.0)) / (2.0 - worley)


def texture_nodes(size: int) -> Tensor:
    """The texture coordinates of the nodes of a size³ texture, [size³, 3] float32 in the order of
    its flattened [k, j, i] layout (x fastest)."""
    axis = torch.arange(size, dtype=torch.float32) / size
    k, j, i = torch.meshgrid(axis, axis, axis, indexing="ij")
    return torch.stack([i, j, k], dim=-1).reshape(-1, 3)


def _normalised(values: Tensor, size: int) -> Tensor:
    """[size³] -> (size, size, size) float32 rescaled to span [0, 1] exactly, so coverage means
    the same for every seed."""
    lo, hi = values.min(), values.max()
    return ((values - lo) / (hi - lo)).to(torch.float32).reshape(size, size, size)


@functools.lru_cache(maxsize=16)
def base_texture(seed: int, size: int = BASE_SIZE) -> Tensor:
    """The Perlin-Worley base texture (size, size, size) float32 [k, j, i] in [0, 1] of `seed`,
    built on first use and cached per (seed, size)."""
    return _normalised(perlin_worley(texture_nodes(size), seed=int(seed)), size)


@functools.lru_cache(maxsize=16)
def detail_texture(seed: int, size: int = DETAIL_SIZE) -> Tensor:
    """The Worley detail texture (size, size, size) float32 [k, j, i] in [0, 1] of `seed`, built on
    first use and cached per (seed, size)."""
    return _normalised(worley_fbm(texture_nodes(size), seed=int(seed) + 5003, frequencies=DETAIL_FREQUENCIES), size)


def tiled_lanes(table, size: int, row, u, v, w):
    """Trilinear lookup with wrap-around in a periodic size³ texture flattened [k, j, i] (x fastest)
    at `row` in `table` (a lane of int32 offsets: a batch's textures one after the other), at
    texture coordinates u, v, w (lanes, any real values; period 1): 8 gathers and 7 lerps, in lanes
    (`ops.lanes`). `size` a power of two: a node's index wraps in floats, exactly (x / size and
    its floor are exact), so no coordinate overflows the int32 index however far it lies."""
    assert size & (size - 1) == 0, f"texture size {size} is not a power of two"
    nodes, fracs = [], []
    for x in (u, v, w):
        x = x * size
        fl = lanes.floor(x)
        fracs.append(x - fl)
        # the mask keeps a non-finite coordinate's index inside the texture; it changes no other
        i = lanes.to_int32(fl - lanes.floor(fl * (1.0 / size)) * size) & (size - 1)
        nodes.append((i, (i + 1) & (size - 1)))
    (x0, x1), (y0, y1), (z0, z1) = nodes
    rows = [row + (z * size + y) * size for z in (z0, z1) for y in (y0, y1)]  # `_CORNERS` order
    return _trilinear([lanes.gather(table, r + x) for r in rows for x in (x0, x1)], fracs)


def sample_tiled(texture: Tensor, uvw: Tensor) -> Tensor:
    """Trilinear lookup in a periodic texture, wrapping around on every axis (`tiled_lanes`).

    `texture`: (N, N, N) [k, j, i] (node (i, j, k) at texture coordinates (i, j, k) / N, N a power
    of two); `uvw`: [n, 3] texture coordinates (any real values; period 1). -> [n] in `uvw`'s dtype."""
    return tiled_lanes(texture.reshape(-1).to(uvw.dtype), texture.shape[0], 0, *uvw.unbind(1))
