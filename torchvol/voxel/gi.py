"""Monte Carlo global illumination of voxel faces (`voxels.gi = { method = "path", bounces, samples }`):
from each primary hit, `samples` paths of up to `bounces` diffuse bounces through the DDA, each
direction cosine-weighted about the face normal from uniforms hashed from (scene seed, pixel,
sample, bounce): deterministic, no generator state, new per accumulation pass (its seeds change).

A bounce's hit adds throughput · (emission + albedo · direct light) and multiplies the throughput
by its albedo; a miss adds throughput · sky and ends the path. With cosine-weighted sampling the
Lambertian BRDF·cos/pdf is the albedo, so the incoming radiance is the plain mean of the path
radiances (no π factors): the furnace room of albedo a, emission e gives e · (1 + a + … + a^B).
GI replaces `voxels.ambient` where it is set. Cost: samples · bounces DDA rays per hit pixel (plus
one shadow ray per light per bounce where `voxels.shadow` is set; unshadowed otherwise)."""

from __future__ import annotations

import math
from typing import Literal

import torch
from pydantic import Field
from torch import Tensor

from .. import noise
from ..schema import Strict

__all__ = ["VoxelGI", "cosine_directions", "path_keys"]


class VoxelGI(Strict):
    """Path-traced diffuse interreflection: `bounces` bounces, `samples` paths per primary hit."""

    method: Literal["path"] = "path"
    bounces: int = Field(1, ge=1, le=16)
    samples: int = Field(8, ge=1, le=4096)


def cosine_directions(normal: Tensor, u1: Tensor, u2: Tensor) -> Tensor:
    """Cosine-weighted unit directions [n, 3] about unit `normal` [n, 3] from uniforms u1, u2 [n] in [0, 1)
    (pdf cos θ / π)."""
    r, phi = torch.sqrt(u1), 2.0 * math.pi * u2
    local_z = torch.sqrt((1.0 - u1).clamp_min(0.0))
    # Duff et al.'s branchless orthonormal basis about the normal
    nx, ny, nz = normal.unbind(1)
    sign = torch.where(nz >= 0, torch.ones_like(nz), -torch.ones_like(nz))
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    t = torch.stack([1.0 + sign * nx * nx * a, sign * b, -sign * nx], dim=1)
    bt = torch.stack([b, sign + ny * ny * a, -ny], dim=1)
    return (r * torch.cos(phi))[:, None] * t + (r * torch.sin(phi))[:, None] * bt + local_z[:, None] * normal


def path_keys(keys: Tensor, samples: int) -> Tensor:
    """Hash cells [n·S, 3] of each primary ray's S paths (ray-major) from its key [n, 3] (sub-pixel
    column, row, scene seed)."""
    j = torch.arange(samples, device=keys.device).repeat(keys.shape[0])
    k = keys.repeat_interleave(samples, dim=0)
    return torch.stack([k[:, 0] * samples + j, k[:, 1], k[:, 2]], dim=1)


def bounce_uniforms(cells: Tensor, bounce: int, dtype) -> tuple[Tensor, Tensor]:
    """The two uniforms [n] of one bounce of the paths `cells` [n, 3]."""
    return tuple(noise.hash3(cells, 0x6100 + 2 * bounce + k, dtype=dtype) for k in (0, 1))
