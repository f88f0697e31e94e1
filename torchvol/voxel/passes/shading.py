"""Shading a voxel hit: its `ShadingPoint` (position, face, UV, material and albedo: face tone and
texture applied), the neighbour AO (`voxels.ao`) into its albedo, and its lit colour: the ambient
(or the GI's incoming light) plus the direct light (`direct.py`), GGX materials reflecting it."""

from __future__ import annotations

import torch
from torch import Tensor

from ...ops.mathops import take_rows
from ...schema.batch import Stacked, per_scene, take
from ..grid import VoxelGrid
from ..materials import default_material, material_table
from ..shade import atlas_sample, face_normal, face_tone, face_uv
from .direct import DirectLight
from .point import ShadingPoint

__all__ = ["Shading"]


class Shading:
    """The materials (`voxels`: the batch's `Stacked` voxels; `plan` its `VoxelPass`), texture
    atlases and AO of `grid`'s hits, lit by `direct`."""

    def __init__(self, voxels: Stacked, plan, grid: VoxelGrid, direct: DirectLight, *, device):
        self.p, self.plan, self.grid, self.direct, self.tracer = voxels, plan, grid, direct, direct.tracer
        self.materials = material_table(voxels.materials)  # (B, M, ...)
        if plan.texture:
            self.atlases = [torch.as_tensor(a, device=device) for a in voxels.texture.atlas]

    def point(self, o: Tensor, d: Tensor, t: Tensor, cell: Tensor, axis: Tensor, mat: Tensor, s: Tensor,
              normal_override: Tensor | None) -> ShadingPoint:
        """The shading record of hits of rays o, d [n, 3] (scenes s [n]) at t [n] on face `axis` [n]
        of `cell` [n, 3] of material `mat` [n]; `normal_override` [n, 3] the shading normal where
        it is not the face's (rounded voxels)."""
        p, g = self.p, self.grid
        x = o + t[:, None] * d
        local = (g.to_grid(x, s) - cell.to(x.dtype)).clamp(0.0, 1.0)
        face_n = face_normal(axis, d)
        uv = face_uv(local, axis)
        M = self.materials.color.shape[1]
        row = s * M + (mat - 1).clamp(0, M - 1)  # the hit's material's row of the (B·M, ...) tables
        of = lambda table: take_rows(table.reshape(-1, *table.shape[2:]), row)  # noqa: E731  (3× table[s, index])
        albedo = of(self.materials.color)
        if self.plan.texture:  # one atlas per scene
            albedo = albedo * per_scene(torch.cat([mat[:, None].to(x.dtype), uv], dim=1), s, len(p),
                                        lambda b, i, q: atlas_sample(self.atlases[b], p.texture.tiles[b], q[:, 0].long(), q[:, 1:]))
        albedo = albedo * face_tone(axis, take(p.face_tones, s))[:, None]
        normal = face_n if normal_override is None else normal_override
        out = ShadingPoint(x=x, cell=cell, axis=axis, face_normal=face_n, normal=normal, uv=uv, albedo=albedo,
                           material=mat.to(x.dtype)[:, None])
        if self.plan.emission:
            out.emission = of(self.materials.emission)
        if self.plan.ggx:
            out.view = -d
            out.roughness = of(self.materials.roughness)[:, None]
            out.metallic = of(self.materials.metallic)[:, None]
        return out

    def ao(self, point: ShadingPoint, s: Tensor, section) -> None:
        """Neighbour AO into the point's albedo (and its `ao`) where `voxels.ao` is set; s [n] the scenes."""
        if self.plan.ao:
            with section("voxels.ao"):
                ao = self.tracer.ao(point.cell, point.face_normal, point.axis, point.uv, take(self.p.ao.gamma, s), s)
                point.albedo = point.albedo * ao[:, None]
                point.ao = ao[:, None]

    def lit(self, point: ShadingPoint, s: Tensor, section, indirect: Tensor | None = None) -> Tensor:
        """The colour [n, 3] of the points of scenes s [n]: ambient (or the GI's `indirect` incoming
        radiance [n, 3]) plus each light's irradiance, shadowed by a DDA ray where `voxels.shadow`
        is set; GGX materials reflect each light by `ggx_reflect` (ambient and indirect light stay
        diffuse: albedo · ambient)."""
        ambient = take(self.p.ambient, s) if indirect is None else indirect
        light, specular = self.direct(point, s, section, ambient)
        lit = point.albedo * light
        if self.plan.ggx:
            pbr = point.albedo * ambient + specular
            lit = torch.where(default_material(point.roughness, point.metallic), lit, pbr)
        return lit + point.emission if self.plan.emission else lit
