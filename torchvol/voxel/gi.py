"""Monte Carlo global illumination of voxel faces (`voxels.gi = { method = "path", bounces, samples }`):
from each primary hit, `samples` paths of up to `bounces` diffuse bounces through the DDA, each
direction cosine-weighted about the face normal from uniforms hashed from (scene seed, pixel,
sample, bounce): deterministic, no generator state, new per accumulation pass (its seeds change).

A bounce's hit adds throughput · (emission + albedo · direct light) and multiplies the throughput
by its albedo; a miss adds throughput · sky and ends the path. With cosine-weighted sampling the
Lambertian BRDF·cos/pdf is the albedo, so the incoming radiance is the plain mean of the path
radiances (no π factors): the furnace room of albedo a, emission e gives e · (1 + a + … + a^B).
GI replaces `voxels.ambient` where it is set. Distance LOD (`lod = { near, far, samples }`): hits
further from the camera trace fewer paths (their first ones: a near hit's paths are the same). Cost: samples · bounces DDA rays per hit pixel (plus
one shadow ray per light per bounce where `voxels.shadow` is set; unshadowed otherwise)."""

from __future__ import annotations

import math
from typing import Literal

import torch
from pydantic import Field, model_validator
from torch import Tensor

from ..noise import lattice as noise
from ..schema.models import Strict

__all__ = ["DistanceLOD", "PathLOD", "VoxelGI", "cosine_directions", "tangent_frame", "lod_counts", "lod_keys", "path_keys"]


class DistanceLOD(Strict):
    """A quality that falls with the world distance of a hit from the camera, from `near` to `far`."""

    near: float = Field(8.0, ge=0.0)
    far: float = Field(32.0, gt=0.0)

    @model_validator(mode="after")
    def _ordered(self):
        if self.far <= self.near:
            raise ValueError(f"far ({self.far}) must exceed near ({self.near})")
        return self


class PathLOD(DistanceLOD):
    """Distance LOD of the paths: hits further from the camera than `near` (world units) trace fewer
    paths, down to `samples` at `far` and beyond (linearly in between, rounded)."""

    samples: int = Field(2, ge=1, le=4096)


class VoxelGI(Strict):
    """Path-traced diffuse interreflection: `bounces` bounces, `samples` paths per primary hit."""

    method: Literal["path"] = "path"
    bounces: int = Field(1, ge=1, le=16)
    samples: int = Field(8, ge=1, le=4096)
    lod: PathLOD | None = None


def lod_counts(distance: Tensor, samples: int, near: Tensor, far: Tensor, far_samples: int) -> Tensor:
    """Paths [n] (long) per hit at camera distance [n]: `samples` up to near [n], `far_samples` from
    far [n] on, linear (rounded) in between."""
    w = ((distance - near) / (far - near)).clamp(0.0, 1.0)
    return torch.round(samples + w * (far_samples - samples)).long()


def lod_keys(keys: Tensor, counts: Tensor, samples: int) -> tuple[Tensor, Tensor]:
    """`path_keys` with counts [n] paths per ray (≤ samples, hashed as the first ones of `samples`)
    -> (hash cells [Σ counts, 3], owner [Σ counts]: each path's ray)."""
    owner = torch.repeat_interleave(torch.arange(keys.shape[0], device=keys.device), counts)
    start = torch.cumsum(counts, 0) - counts
    j = torch.arange(owner.shape[0], device=keys.device) - start[owner]
    k = keys[owner]
    return torch.stack([k[:, 0] * samples + j, k[:, 1], k[:, 2]], dim=1), owner


def tangent_frame(normal: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit tangents [n, 3], [n, 3] completing unit `normal` [n, 3] to an orthonormal basis
    (Duff et al.'s branchless construction)."""
    nx, ny, nz = normal.unbind(1)
    sign = torch.where(nz >= 0, torch.ones_like(nz), -torch.ones_like(nz))
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    t = torch.stack([1.0 + sign * nx * nx * a, sign * b, -sign * nx], dim=1)
    bt = torch.stack([b, sign + ny * ny * a, -ny], dim=1)
    return t, bt


def cosine_directions(normal: Tensor, u1: Tensor, u2: Tensor) -> Tensor:
    """Cosine-weighted unit directions [n, 3] about unit `normal` [n, 3] from uniforms u1, u2 [n] in [0, 1)
    (pdf cos θ / π)."""
    r, phi = torch.sqrt(u1), 2.0 * math.pi * u2
    local_z = torch.sqrt((1.0 - u1).clamp_min(0.0))
    t, bt = tangent_frame(normal)
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
