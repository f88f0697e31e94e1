"""Voxel surface materials.

`Material` is a `voxels.materials` entry: a colour `[r, g, b]` (the albedo: the first form, kept)
or a table `{ color, roughness = 1, metallic = 0, emission = [0, 0, 0] }`; emission is the radiance
leaving the material's faces; roughness and metallic select the GGX reflectance (`ggx.py`) where
they differ from the default (roughness 1, metallic 0: the seed's "fully diffuse", Lambert).
`material_table` reads a batch's entries as (B, M, ...) tensors.

The `VOXEL_MATERIALS` registry holds the reflectance models: each kind is its schema model and its
function `fn(normal [n, 3], light_dir [n, 3], irradiance [n, 3], visibility [n]) -> reflected light
[n, 3]` per unit albedo: what one light adds at a surface point, multiplied into the material's
albedo by the surface pass."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from pydantic import Field, field_validator, model_validator
from torch import Tensor

from ..schema.models import Strict, Vec3, nonneg
from ..schema.registry import Registry
from .shade import lambert


class Material(Strict):
    """A voxel material: albedo `color`, GGX `roughness` and `metallic` (0..1; roughness 1 and
    metallic 0 is Lambert) and `emission` (the radiance leaving its faces). A bare `[r, g, b]` is
    `{ color = [r, g, b] }`."""

    color: Vec3 = (1.0, 1.0, 1.0)
    roughness: float = Field(1.0, ge=0.0, le=1.0)
    metallic: float = Field(0.0, ge=0.0, le=1.0)
    emission: Vec3 = (0.0, 0.0, 0.0)
    _c = field_validator("color", "emission")(lambda v: nonneg(v))

    @model_validator(mode="before")
    @classmethod
    def _colour_form(cls, v):
        if isinstance(v, (list, tuple)) or (hasattr(v, "shape") and not isinstance(v, dict)):
            return {"color": v}
        return v


@dataclass(frozen=True)
class MaterialTable:
    """A batch's materials as tensors: `color`, `emission` (B, M, 3); `roughness`, `metallic` (B, M)."""

    color: Tensor
    emission: Tensor
    roughness: Tensor
    metallic: Tensor


def material_table(materials: list) -> MaterialTable:
    """`materials`: a batch's `voxels.materials`, one `Stacked` per entry -> the (B, M, ...) table."""
    return MaterialTable(*(torch.stack([getattr(m, key) for m in materials], dim=1)
                           for key in ("color", "emission", "roughness", "metallic")))


def any_ggx(materials: list) -> bool:
    """Whether some material of some scene of a batch (one `Stacked` per entry) is GGX, not the default Lambert."""
    return any(bool((~default_material(m.roughness, m.metallic)).any()) for m in materials)


def default_material(roughness: Tensor, metallic: Tensor) -> Tensor:
    """Where a material [n] is the default Lambert one (roughness 1, metallic 0): shaded as before, bit for bit."""
    return (roughness >= 1) & (metallic <= 0)


def diffuse(normal: Tensor, light_dir: Tensor, irradiance: Tensor, visibility: Tensor) -> Tensor:
    """Lambert: irradiance · max(n · l, 0) · visibility (the seed's faces)."""
    return irradiance * (lambert(normal, light_dir) * visibility)[:, None]


VOXEL_MATERIALS = Registry("voxel material")
VOXEL_MATERIALS.register("diffuse", Vec3, diffuse)
