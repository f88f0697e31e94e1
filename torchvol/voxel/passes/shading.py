"""Shading a voxel hit: its `ShadingPoint` (position, face, UV, material and albedo: face tone and
texture applied), the neighbour AO (`voxels.ao`) into its albedo, and its lit colour: the ambient
(or the GI's incoming light) plus the direct light (`direct.py`), GGX materials reflecting it.
Each is `look.py`'s lanes: on torch columns here, piece by piece, or all of them as one Dr.Jit
kernel over a chunk's hits (`Shading.shade`, where `look.fusable`)."""

from __future__ import annotations

import torch
from torch import Tensor

from ...ops import lanes
from ...runtime.compilation import traced_columns
from ...schema.batch import Stacked, take
from ..grid import VoxelGrid
from .direct import DirectLight, point_lanes_view
from .look import (
    ao_of,
    direct_lanes,
    fusable,
    lit_lanes,
    look_inputs,
    point_lanes_of,
    visible_beside,
)
from .point import ShadingPoint

__all__ = ["Shading"]


class Shading:
    """The look of `grid`'s hits (`voxels`: the batch's `Stacked` voxels; `plan` its `VoxelPass`):
    their materials, texels, AO and the light of `direct`; `fused` where `shade` is one kernel."""

    def __init__(self, voxels: Stacked, plan, grid: VoxelGrid, direct: DirectLight, occluder_lanes=None):
        self.p, self.plan, self.grid, self.direct, self.tracer = voxels, plan, grid, direct, direct.tracer
        self.fused = self.tracer.drjit and fusable(plan, direct.lights)
        self.beside = {use.light: use for use in plan.shadows if use.terrain or use.occluders}  # shadow rays leaving the voxels
        self.occluder_lanes = occluder_lanes

    def point(self, o: Tensor, d: Tensor, t: Tensor, cell: Tensor, axis: Tensor, mat: Tensor, s: Tensor,
              normal_override: Tensor | None) -> ShadingPoint:
        """The shading record of hits of rays o, d [n, 3] (scenes s [n]) at t [n] on face `axis` [n]
        of `cell` [n, 3] of material `mat` [n]; `normal_override` [n, 3] the shading normal where
        it is not the face's (rounded voxels)."""
        if self.tracer.drjit:  # one small kernel, not ~60 torch passes over the hits
            return self._kernel(o, d, t, cell, axis, mat, s, normal_override, lit=False)[1]
        q = self.direct.inputs(s, o, surface=True)
        col = lanes.columns
        point = point_lanes_of(q, col(o), col(d), t, col(cell), axis, mat,
                               None if normal_override is None else col(normal_override))
        return self._record(point, cell, axis)

    def _record(self, point, cell: Tensor, axis: Tensor) -> ShadingPoint:
        """`look.point_lanes_of`'s point on torch columns as a `ShadingPoint`; the emission, view,
        roughness and metallic where the plan reads them."""
        vec = lambda x: torch.stack(x, dim=1)  # noqa: E731
        face = vec(point.face_normal)
        out = ShadingPoint(x=vec(point.x), cell=cell, axis=axis, face_normal=face,
                           normal=face if point.normal is point.face_normal else vec(point.normal),
                           uv=vec([point.u, point.v]), albedo=vec(point.albedo), material=point.material[:, None])
        if self.plan.emission:
            out.emission = vec(point.emission)
        if self.plan.ggx:
            out.view = vec(point.view)
            out.roughness, out.metallic = point.roughness[:, None], point.metallic[:, None]
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
        col = lanes.columns
        return torch.stack(lit_lanes(point_lanes_view(point), col(ambient), col(light),
                                     None if isinstance(specular, int) else col(specular),
                                     ggx=self.plan.ggx, emission=self.plan.emission), dim=1)

    def shade(self, o: Tensor, d: Tensor, t: Tensor, cell: Tensor, axis: Tensor, mat: Tensor, s: Tensor,
              normal_override: Tensor | None, section, indirect=None) -> tuple[Tensor, ShadingPoint]:
        """`point`, `ao` and `lit` of the hits (as `point` takes them) -> (colour [n, 3], their
        `ShadingPoint`): one Dr.Jit kernel where `fused` (the walks are kernels, no GI) and every
        shadow ray that leaves the voxels has the lanes of what it crosses (`occluder_lanes`): the
        shadow walks and those lanes inside it; else piece by piece. `indirect(point) -> [n, 3]`:
        the GI's incoming light at the hits (their AO applied), in place of the ambient."""
        inside = None
        if self.fused and self.beside and o.shape[0] and self.occluder_lanes is not None:
            inside = self.occluder_lanes(self.beside, s)  # the terrain's and the volumes' lanes, where they have them
        if not self.fused or o.shape[0] == 0 or (self.beside and inside is None):
            with section("voxels.shade"):
                point = self.point(o, d, t, cell, axis, mat, s, normal_override)
            self.ao(point, s, section)
            return self.lit(point, s, section, None if indirect is None else indirect(point)), point
        with section("voxels.shade"):
            out = self._kernel(o, d, t, cell, axis, mat, s, normal_override, lit=True, inside=inside)
        for k in (inside or {}).values():
            k.count()
        for name in (["voxels.ao"] if self.plan.ao else []) + [n for use in self.plan.shadows for n in use.names()]:
            with section(name):  # listed in the stats; their time is the shading's
                pass
        return out

    def _kernel(self, o, d, t, cell, axis, mat, s, normal_override, *, lit: bool,
                inside: dict | None = None) -> tuple[Tensor | None, ShadingPoint]:
        """`shade` as one Dr.Jit kernel: `look`'s lanes in the order `point`, `ao` and `lit` run
        them; out of it only what the colour, the AOVs and the reflections read. `lit` False: the
        point alone (`point` where the walks are kernels) -> (None, its `ShadingPoint`). `inside`:
        the occluder lanes of the shadow rays that leave the voxels (by light), traced where the
        voxels let the light through, as the pieces trace them."""
        plan = self.plan
        shadowed = {use.light: use for use in plan.shadows} if lit else {}
        wanted = {"colour": 3 * lit, "x": 3, "face_normal": 3, "normal": 3 * (normal_override is not None), "u": 1, "v": 1,
                  "albedo": 3, "material": 1, "emission": 3 * plan.emission, "roughness": plan.ggx, "metallic": plan.ggx,
                  "ao": plan.ao and lit, "shadow": bool(shadowed)}
        wanted = {k: int(w) for k, w in wanted.items() if w}

        def kernel(lane):
            q = look_inputs(self.p, plan, self.direct.tables, self.grid, self.direct.lights, s, lanes.per_scene_lanes(s),
                            lanes.ints_of, lanes.floats_of, kernel=True, walks=lit, light=lit)
            point = point_lanes_of(q, lanes.vector_lanes(o), lanes.vector_lanes(d), lane(t),
                                   [lanes.ints_of(c) for c in cell.unbind(1)], lanes.ints_of(axis), lanes.ints_of(mat),
                                   None if normal_override is None else lanes.vector_lanes(normal_override))
            if lit:
                if plan.ao:
                    point.ao = ao_of(q, point)
                    point.albedo = [a * point.ao for a in point.albedo]
                visible = visible_beside(q, inside) if shadowed else None
                light, specular, point.shadow = direct_lanes(q, point, q.ambient, visible, shadowed)
                point.colour = lit_lanes(point, q.ambient, light, specular, ggx=plan.ggx, emission=plan.emission)
            return [x for k in wanted for x in (getattr(point, k) if wanted[k] == 3 else [getattr(point, k)])]

        also = lambda: [e for k in (inside or {}).values() for e in k.evals()]  # noqa: E731
        out = dict(zip(wanted, traced_columns(kernel, o, tuple(wanted.values()), also)))
        one = lambda k: out[k][:, None] if k in out else None  # noqa: E731
        point = ShadingPoint(x=out["x"], cell=cell, axis=axis, face_normal=out["face_normal"],
                             normal=out.get("normal", out["face_normal"]), uv=torch.stack([out["u"], out["v"]], dim=1),
                             albedo=out["albedo"], material=one("material"), emission=out.get("emission"),
                             view=-d if plan.ggx else None, roughness=one("roughness"), metallic=one("metallic"),
                             ao=one("ao"), shadow=one("shadow"))
        return out.get("colour"), point
