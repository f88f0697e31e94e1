"""Voxel surface materials: the `VOXEL_MATERIALS` registry. Each kind is its schema model (a
`voxels.materials` entry) and its function `fn(normal [n, 3], light_dir [n, 3], irradiance [n, 3],
visibility [n]) -> reflected light [n, 3]` per unit albedo: what one light adds at a surface
point, multiplied into the material's albedo by the surface pass."""

from __future__ import annotations

from torch import Tensor

from ..registry import Registry
from ..schema import Vec3
from .shade import lambert


def diffuse(normal: Tensor, light_dir: Tensor, irradiance: Tensor, visibility: Tensor) -> Tensor:
    """Lambert: irradiance · max(n · l, 0) · visibility (the seed's faces)."""
    return irradiance * (lambert(normal, light_dir) * visibility)[:, None]


VOXEL_MATERIALS = Registry("voxel material")
VOXEL_MATERIALS.register("diffuse", Vec3, diffuse)
