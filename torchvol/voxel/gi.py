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

from typing import Literal

import torch
from pydantic import Field, model_validator
from torch import Tensor

from ..geometry.scatter import lambert_bounce
from ..noise import lattice as noise
from ..ops import lanes
from ..schema.models import Strict

__all__ = ["DistanceLOD", "PathLOD", "VoxelGI", "bounce_direction_lanes", "bounce_uniform_lanes", "lod_counts", "lod_keys",
           "path_keys"]


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


def path_keys(keys: Tensor, samples: int) -> Tensor:
    """Hash cells [n·S, 3] of each primary ray's S paths (ray-major) from its key [n, 3] (sub-pixel
    column, row, scene seed)."""
    j = torch.arange(samples, device=keys.device).repeat(keys.shape[0])
    k = keys.repeat_interleave(samples, dim=0)
    return torch.stack([k[:, 0] * samples + j, k[:, 1], k[:, 2]], dim=1)


def bounce_uniform_lanes(cells: list, bounce: int, like) -> tuple:
    """The two uniforms in [0, 1) (lanes of `like`'s float type) of one bounce of the paths whose
    hash cells are `cells` (three int32 lanes holding the keys' low 32 bits, `noise.int32_bits`):
    `noise.hash3_lanes`' top 24 bits · 2⁻²⁴, as float32 `noise.hash3` gives them."""
    return tuple(lanes.to_float((noise.hash3_lanes(*cells, 0x6100 + 2 * bounce + k) >> 8) & 0xFFFFFF, like) * 2.0**-24
                 for k in (0, 1))


def bounce_direction_lanes(normal: list, u1, u2) -> list:
    """The cosine-weighted direction (three lanes) about unit `normal` (three lanes) from uniforms
    u1, u2 (lanes): the Lambert bounce every surface of the path tracer takes (`geometry.scatter`)."""
    return lambert_bounce(None, normal, None, [u1, u2])[0]
