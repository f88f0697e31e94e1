"""The per-hit shading record the voxel passes hand each other (`shading.py` makes it)."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

__all__ = ["POINT_AOVS", "ShadingPoint"]

POINT_AOVS = ("normal", "uv", "material", "ao", "shadow", "roughness", "metallic")  # the AOVs a point holds


@dataclass
class ShadingPoint:
    """The per-hit shading record of n hits, filled in as the passes run: `x` [n, 3] the world
    position; `cell` [n, 3] long and `axis` [n] long the hit cell and face; `face_normal` [n, 3]
    the face's, `normal` [n, 3] the shading one (a rounded voxel's); `uv` [n, 2]; `albedo` [n, 3]
    (AO and the cones' visibility multiply it); `material` [n, 1] the material id. With
    `voxels.emission`: `emission` [n, 3]; with GGX materials: `view` [n, 3] (towards the eye),
    `roughness`, `metallic` [n, 1]. `ao` [n, 1] once AO or the cones ran, `shadow` [n, 1] the
    first shadowed light's visibility once it was traced."""

    x: Tensor
    cell: Tensor
    axis: Tensor
    face_normal: Tensor
    normal: Tensor
    uv: Tensor
    albedo: Tensor
    material: Tensor
    emission: Tensor | None = None
    view: Tensor | None = None
    roughness: Tensor | None = None
    metallic: Tensor | None = None
    ao: Tensor | None = None
    shadow: Tensor | None = None

    def aov(self, name: str) -> Tensor | None:
        """The point's value [n, C] of AOV `name`; None where it holds none (not computed, or not its AOV)."""
        return getattr(self, name) if name in POINT_AOVS else None
