"""Per-ray random numbers of a render, hashed from (seed, ray): the same seed gives the same values
whatever the chunking or batch, with no generator state. Sub-pixel jitter, march dither and
the keys of voxel GI paths."""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from ..noise import lattice as noise
from ..ops.mathops import take_rows
from .camera import Rays, strata_shape


def subpixel_jitter(start: int, stop: int, *, seeds: Tensor, width: int, height: int, spp: int,
                    dtype: torch.dtype) -> Tensor | None:
    """Sub-pixel offsets [n, 2] in (−0.5, 0.5) of rays start:stop of the flat ray order (scene,
    row, column, sub-sample): stratum + a hash of (seed, ray). `seeds`: (B,) one per scene. None
    (stratum centres, the pixel centre) for spp == 1."""
    if spp == 1:
        return None
    ids = torch.arange(start, stop, device=seeds.device)
    nx, ny = strata_shape(spp)
    per_scene = width * height * spp
    sample, scene = ids % spp, ids // per_scene
    cells = torch.stack([ids % per_scene, seeds[scene], torch.zeros_like(ids)], dim=1)
    xi = torch.stack([noise.hash3(cells, 0x717E + k, dtype=torch.float64) for k in (0, 1)], dim=1)
    strata = torch.stack([sample % nx, sample // nx], dim=1).to(torch.float64)
    off = (strata + xi) / torch.tensor([nx, ny], dtype=torch.float64, device=ids.device) - 0.5
    return off.clamp(-0.5 + 1e-7, 0.5 - 1e-7).to(dtype)


def march_dither(rays: Rays, mode: Literal["none", "hash", "sin"], *, scale: float, seeds: Tensor, height: int,
                 spp: int, kernel: bool = False) -> Tensor | None:
    """The march's start offset per ray [n] (`march.dither`): None, a hash of (seed, pixel,
    sub-sample) in [0, 1) (`kernel`: hashed in a Dr.Jit kernel, the same bits), or the seeds'
    fract(sin(px.x·73 + px.y·311)·43758.5453)·`scale` in GL pixel coordinates (row 0 at the
    bottom). Chunks hold whole pixels."""
    if mode == "none":
        return None
    if mode == "sin":
        px = rays.pixel[:, 0]
        py = height - 1 - rays.pixel[:, 1]
        x = torch.sin((px * 73 + py * 311).to(rays.origins.dtype)) * 43758.5453
        return scale * (x - torch.floor(x))
    return noise.hash3_columns(*ray_key_columns(rays, seeds=seeds, spp=spp), 0x5EED, dtype=rays.origins.dtype,
                               kernel=kernel)


def ray_keys(rays: Rays, *, seeds: Tensor, spp: int) -> Tensor:
    """Each ray's hash cell [n, 3] long: (column·spp + sub-sample, row, its scene's seed); `seeds`
    (B,). Chunks hold whole pixels."""
    return torch.stack(ray_key_columns(rays, seeds=seeds, spp=spp), dim=1)


def ray_key_columns(rays: Rays, *, seeds: Tensor, spp: int) -> tuple[Tensor, Tensor, Tensor]:
    """`ray_keys`' three columns [n] long."""
    column = rays.pixel[:, 0]
    if spp > 1:  # (one sub-sample: the column itself)
        column = column * spp + torch.arange(len(rays), device=rays.pixel.device) % spp
    return column, rays.pixel[:, 1], take_rows(seeds, rays.scene_index)
