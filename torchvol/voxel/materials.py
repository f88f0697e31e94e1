"""Voxel surface materials.

`Material` is a `voxels.materials` entry: a colour `[r, g, b]` (the albedo: the first form, kept)
or a table `{ color, roughness = 1, metallic = 0, emission = [0, 0, 0] }`; emission is the radiance
leaving the material's faces; roughness and metallic select the GGX reflectance (`ggx.py`) where
they differ from the default (roughness 1, metallic 0: the seed's "fully diffuse", Lambert).
`material_table` reads a batch's entries as (B, M, ...) tensors.

The `VOXEL_MATERIALS` registry holds the reflectance models: each kind is its schema model and its
function in lanes (`ops.lanes`) `fn(normal, light_dir, irradiance, visibility) -> reflected light`
(three lanes each, `visibility` one) per unit albedo: what one light adds at a surface point,
multiplied into the material's albedo by the surface pass (`passes.look.direct_lanes`)."""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import torch
from pydantic import Field, field_validator, model_validator
from torch import Tensor

from ..geometry.scatter import facing
from ..ops import lanes
from ..schema.models import Strict, Vec3, nonneg
from ..schema.registry import Registry


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


def diffuse(normal: list, light_dir: list, irradiance: list, visibility) -> list:
    """Lambert in lanes (`ops.lanes`): irradiance · max(n · l, 0) · visibility (three lanes each,
    `visibility` one or a number; the seed's faces)."""
    lit = facing(normal, light_dir) * visibility
    return [e * lit for e in irradiance]


def material_lanes(materials: MaterialTable, s: Tensor, ints, floats):
    """The materials (a batch's `material_table`) of rays of scenes `s` [n] as lanes (`ints`,
    `floats`: tensors -> lanes): look(material id, texels or None) -> the hit's albedo (three
    lanes; the texels times the colour, as the marched faces take it), roughness, metallic,
    whether it is GGX and the light its faces emit (`glow`, three lanes)."""
    count = materials.color.shape[1]
    first = ints((s * count).to(torch.int32))  # each lane's scene's first row of the tables
    colour = [floats(c.reshape(-1)) for c in materials.color.unbind(2)]
    glow = [floats(c.reshape(-1)) for c in materials.emission.unbind(2)]
    rough, metal = floats(materials.roughness.reshape(-1)), floats(materials.metallic.reshape(-1))

    def look(material, texels) -> SimpleNamespace:
        i = first + lanes.clamp(material - 1, 0, count - 1)  # (id 0, no hit: the first material, unused)
        rgh, mtl = lanes.gather(rough, i), lanes.gather(metal, i)
        albedo = [lanes.gather(c, i) for c in colour]
        if texels is not None:
            albedo = [a * x for a, x in zip(albedo, texels)]
        return SimpleNamespace(albedo=albedo, roughness=rgh, metallic=mtl, ggx=(rgh < 1.0) | (mtl > 0.0),
                               glow=[lanes.gather(c, i) for c in glow])

    return look


VOXEL_MATERIALS = Registry("voxel material")
VOXEL_MATERIALS.register("diffuse", Vec3, diffuse)
