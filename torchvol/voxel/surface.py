"""The voxel surface pass of a render: a batch's voxel grids and the per-chunk pipeline
(traversal, variants, shading, AO, shadow rays, fog, glow) assembled from dda/shade/grid.

`VoxelSurface.run(o, d, s, background, section)` returns, per ray [n]: ``hit``, ``t`` (world
distance of the first hit, inf for misses), ``color`` [n, 3] (what the ray sees behind any volume:
the shaded surface where hit, else `background`, with fog and glow applied), ``steps`` and the AOVs
the plan calls for (``normal`` [n, 3], ``uv`` [n, 2], ``material``, ``ao``, ``shadow``,
``roughness``, ``metallic`` [n, 1]).

GGX materials (`ggx.py`) shade the sun and, with `voxels.reflections`, add a mirror reflection
ray traced through the same DDA and shaded the same way (AO, shadows, GGX; not the rounded, glow
or fog variants), the sky where it misses, weighted by F · (1 − roughness)²: rough surfaces use the
mirror direction faded out, not a sampled lobe (an approximation). Default materials (roughness 1,
metallic 0) stay Lambert, bit for bit.
Every per-scene value arrives as a (B, ...) tensor of the batch's `Stacked` voxels, or is handled
scene by scene (occupancy, texture atlas, the glow's SDF).
"""

from __future__ import annotations

from contextlib import nullcontext
from typing import Callable, Sequence

import torch
from torch import Tensor

from .. import sdf
from ..aovs import AOVS
from ..batch import Stacked, per_scene, take
from ..lights import LightSource
from .dda import Hits, hybrid_traverse, traverse
from .ggx import f0_of, f_schlick, ggx_reflect
from .grid import VoxelGrid
from .materials import VOXEL_MATERIALS, default_material, material_table
from .shade import atlas_sample, face_normal, face_tone, face_uv, rounded_refine, voxel_ao

__all__ = ["VoxelSurface"]

SURFACE_AOVS = ("normal", "uv", "material", "ao", "shadow", "roughness", "metallic")
REFLECTION_OFFSET = 1e-3  # the seed's hitPos + normal · 0.001, in voxels


class VoxelSurface:
    """One batch's voxel grids and shading parameters (`voxels`: the batch's `Stacked` voxels),
    lit by `lights`; `plan` the batch's `VoxelPass`; `aovs` the AOV names to output; `sky(directions
    [n, 3], s [n]) -> [n, 3]` what reflection rays that miss see (None: black)."""

    def __init__(self, voxels: Stacked, lights: Sequence[LightSource], plan, aovs: Sequence[str], *, dtype, device,
                 compiled: bool = False, sky: Callable[[Tensor, Tensor], Tensor] | None = None):
        self.p, self.lights, self.plan, self.compiled, self.sky = voxels, list(lights), plan, compiled, sky
        self.grid = VoxelGrid.from_specs(voxels.models, dtype=dtype, device=device, with_distance=plan.traversal == "hybrid")
        self.aov_names = [a for a in aovs if a in SURFACE_AOVS]
        self.material = VOXEL_MATERIALS["diffuse"]
        self.materials = material_table(voxels.materials)  # (B, M, ...)
        if plan.texture:
            self.atlases = [torch.as_tensor(a, device=device) for a in voxels.texture.atlas]
        self.steps_total = 0

    # -- helpers ---------------------------------------------------------------------------------

    def _traverse(self, o: Tensor, d: Tensor, s: Tensor, *, max_steps: int, t_min=None, t_max=None, visit=None,
                  plain=False) -> Hits:
        """World rays [n, 3] of scenes s [n] through their grids (t in world units)."""
        g = self.grid
        og, dg = g.to_grid(o, s), d / g.voxel_size[s, None]
        lookup = lambda c, ids: g.lookup(c, s[ids])
        lo, hi = g.lo[s], g.hi[s]
        if self.plan.traversal == "hybrid" and visit is None and not plain:
            return hybrid_traverse(og, dg, lookup, lambda c, ids: g.empty_radius(c, s[ids]), lo, hi,
                                   max_steps=max_steps, t_min=t_min, compiled=self.compiled)
        return traverse(og, dg, lookup, lo, hi, max_steps=max_steps, t_min=t_min, t_max=t_max, visit=visit,
                        compiled=self.compiled)

    def _visibility(self, p: Tensor, s: Tensor, light: LightSource, steps: int, toward=None) -> Tensor:
        """Visibility [n] (1 lit, 0 occluded) of points p [n, 3] towards `light` (a shadow ray that
        ends at the light)."""
        if p.shape[0] == 0:
            return p.new_zeros(0)
        toward = light.toward(p, s) if toward is None else toward
        t_max = None if light.directional else toward.distance
        h = self._traverse(p, toward.direction, s, max_steps=steps, t_max=t_max, plain=True)
        return (~h.hit).to(p.dtype)

    def _glow_and_fog(self, o: Tensor, s: Tensor):
        """The per-cell callback of the DDA when glow or fog accumulate, and its accumulators."""
        p, g, n, dt = self.p, self.grid, o.shape[0], o.dtype
        acc = dict(glow=o.new_zeros(n), fog_tau=o.new_zeros(n), fog_light=o.new_zeros(n, 3))

        def visit(ids, cells, t_in, t_out, hit):
            sc = s[ids]
            if self.plan.glow:  # the seed's sdSomeShape(vec3(mapPos)): the cell corner, each scene's own SDF
                corner = g.to_world(cells.to(dt), sc)
                dist = per_scene(corner, sc, len(p), lambda b, _, q: sdf.evaluate(p.occupancy[b].sdf.shape, q))
                acc["glow"].index_add_(0, ids, take(p.glow.intensity, sc) / (take(p.glow.epsilon, sc) + dist * dist))
            if self.plan.fog:
                e = (~hit).nonzero().squeeze(1)
                if e.numel():
                    ie, se = ids[e], sc[e]
                    centre = g.to_world(cells[e].to(dt) + 0.5, se)
                    f = p.fog
                    sigma = take(f.density, se) * torch.exp(-(centre[:, 1] - take(f.base, se)) / take(f.scale_height, se))
                    tau = sigma * (t_out[e] - t_in[e]).clamp_min(0.0)
                    acc["fog_tau"].index_add_(0, ie, tau)
                    light = o.new_zeros(e.numel(), 3)
                    for source in self.lights:
                        toward = source.toward(centre, se)
                        vis = self._visibility(centre, se, source, f.shadow_steps, toward)
                        light = light + toward.irradiance * vis[:, None]
                    acc["fog_light"].index_add_(0, ie, (tau * torch.exp(-acc["fog_tau"][ie]))[:, None] * light * take(f.color, se))

        return visit, acc

    # -- the pass --------------------------------------------------------------------------------

    def run(self, o: Tensor, d: Tensor, s: Tensor, background: Tensor,
            section: Callable[[str], object] = lambda name: nullcontext()) -> dict[str, Tensor]:
        """o, d [n, 3] world rays (d unit); s [n] scenes; background [n, 3]."""
        p, n = self.p, o.shape[0]
        visit, acc = self._glow_and_fog(o, s) if self.plan.glow or self.plan.fog else (None, None)
        with section("voxels.dda"):
            hits = self._traverse(o, d, s, max_steps=p.max_steps, visit=visit)
        steps = hits.steps.clone()
        hit, t, cell, axis, mat = hits.hit, hits.t, hits.cell, hits.axis, hits.material
        normal_override = None
        if self.plan.rounded:
            with section("voxels.rounded"):
                hit, t, cell, axis, mat, normal_override, extra = self._rounded(o, d, s, hits)
                steps = steps + extra
        self.steps_total += int(steps.sum())

        ids = hit.nonzero().squeeze(1)
        out_color = background.clone()
        aovs = {k: o.new_zeros(n, AOVS[k].channels) for k in self.aov_names}
        if ids.numel():
            sh = s[ids]
            with section("voxels.shade"):
                surface = self._surface(o[ids], d[ids], t[ids], cell[ids], axis[ids], mat[ids], sh,
                                        None if normal_override is None else normal_override[ids])
            self._ao(surface, sh, section)
            out_color[ids] = self._lit(surface, sh, section)
            if self.plan.reflections:
                with section("voxels.reflections"):
                    self._reflect(out_color, ids, surface, d[ids], sh, self.plan.reflections, section)
            for k in self.aov_names:
                aovs[k][ids] = surface[k]
        if self.plan.fog:
            out_color = out_color * torch.exp(-acc["fog_tau"])[:, None] + acc["fog_light"]
        if self.plan.glow:
            out_color = out_color + acc["glow"][:, None] * take(p.glow.color, s)
        t_hit = torch.where(hit, t, torch.full_like(t, torch.inf))
        return dict(hit=hit, t=t_hit, color=out_color, steps=steps, aovs=aovs)

    def _ao(self, surface: dict[str, Tensor], s: Tensor, section) -> None:
        """Neighbour AO into the surface's albedo (and its AOV) where `voxels.ao` is set."""
        if self.plan.ao:
            with section("voxels.ao"):
                ao = voxel_ao(lambda c: (self.grid.lookup(c, s.repeat(8)) > 0), surface["cell"], surface["face_normal"],
                              surface["axis"], surface["uv"], gamma=take(self.p.ao.gamma, s))
                surface["albedo"] = surface["albedo"] * ao[:, None]
                surface["ao"] = ao[:, None]

    def _reflect(self, color: Tensor, ids: Tensor, surface: dict[str, Tensor], d: Tensor, s: Tensor, bounces: int,
                 section) -> None:
        """Adds into color[ids] [n, 3] the mirror reflection of the hits `surface` seen along d [n, 3]
        (scenes s [n]), weighted by Fresnel · (1 − roughness)²; only where that weight is not 0."""
        rough = surface["roughness"][:, 0]
        f = f_schlick(f0_of(surface["albedo"], surface["metallic"][:, 0]), (surface["normal"] * -d).sum(-1, keepdim=True))
        weight = f * ((1.0 - rough) * (1.0 - rough))[:, None]
        live = (weight > 0).any(dim=1).nonzero().squeeze(1)
        if not live.numel():
            return
        n, dl, sl = surface["normal"][live], d[live], s[live]
        r = dl - 2.0 * (dl * n).sum(-1, keepdim=True) * n
        start = surface["x"][live] + (REFLECTION_OFFSET * self.grid.voxel_size[sl])[:, None] * surface["face_normal"][live]
        color[ids[live]] += weight[live] * self._trace_shade(start, r, sl, bounces, section)

    def _trace_shade(self, o: Tensor, d: Tensor, s: Tensor, bounces: int, section) -> Tensor:
        """Radiance [n, 3] along reflection rays o, d [n, 3]: the shaded surface they hit (with its
        own reflection while bounces remain), else the sky."""
        h = self._traverse(o, d, s, max_steps=self.p.reflections.steps, plain=True)
        self.steps_total += int(h.steps.sum())
        color = o.new_zeros(o.shape[0], 3) if self.sky is None else self.sky(d, s).clone()
        ids = h.hit.nonzero().squeeze(1)
        if ids.numel():
            sh = s[ids]
            surface = self._surface(o[ids], d[ids], h.t[ids], h.cell[ids], h.axis[ids], h.material[ids], sh, None)
            self._ao(surface, sh, section)
            color[ids] = self._lit(surface, sh, section)
            if bounces > 1:
                self._reflect(color, ids, surface, d[ids], sh, bounces - 1, section)
        return color

    def _surface(self, o, d, t, cell, axis, mat, s, normal_override) -> dict[str, Tensor]:
        """Hit position, normal, UV, material and albedo (face tone and texture applied) of hits."""
        p, g = self.p, self.grid
        x = o + t[:, None] * d
        local = (g.to_grid(x, s) - cell.to(x.dtype)).clamp(0.0, 1.0)
        face_n = face_normal(axis, d)
        uv = face_uv(local, axis)
        index = (mat - 1).clamp(0, self.materials.color.shape[1] - 1)
        albedo = self.materials.color[s, index]
        if self.plan.texture:  # one atlas per scene
            albedo = albedo * per_scene(torch.cat([mat[:, None].to(x.dtype), uv], dim=1), s, len(p),
                                        lambda b, i, q: atlas_sample(self.atlases[b], p.texture.tiles[b], q[:, 0].long(), q[:, 1:]))
        albedo = albedo * face_tone(axis, take(p.face_tones, s))[:, None]
        normal = face_n if normal_override is None else normal_override
        out = dict(x=x, cell=cell, axis=axis, face_normal=face_n, normal=normal, uv=uv, albedo=albedo,
                   material=mat.to(x.dtype)[:, None])
        if self.plan.emission:
            out["emission"] = self.materials.emission[s, index]
        if self.plan.ggx:
            out.update(view=-d, roughness=self.materials.roughness[s, index][:, None],
                       metallic=self.materials.metallic[s, index][:, None])
        return out

    def _lit(self, surface: dict[str, Tensor], s: Tensor, section) -> Tensor:
        """Ambient plus each light's irradiance, shadowed by a DDA ray where `voxels.shadow` is set;
        GGX materials reflect each light by `ggx_reflect` (ambient stays diffuse: albedo · ambient)."""
        p, light = self.p, take(self.p.ambient, s)
        ambient = light
        specular = []
        shadows = {use.light: use for use in self.plan.shadows}
        for l, source in enumerate(self.lights):
            toward = source.toward(surface["x"], s)
            vis = torch.ones_like(surface["x"][:, 0])
            if l in shadows:
                with section(shadows[l].name):
                    start = surface["x"] + take(p.shadow.offset, s)[:, None] * surface["face_normal"]
                    vis = self._visibility(start, s, source, p.shadow.steps, None if source.directional else source.toward(start, s))
                if "shadow" not in surface:
                    surface["shadow"] = vis[:, None]
            light = light + self.material.fn(surface["normal"], toward.direction, toward.irradiance, vis)
            if self.plan.ggx:
                specular.append(ggx_reflect(surface["normal"], surface["view"], toward.direction, surface["albedo"],
                                            surface["roughness"][:, 0], surface["metallic"][:, 0])
                                * toward.irradiance * vis[:, None])
        lit = surface["albedo"] * light
        if self.plan.ggx:
            pbr = surface["albedo"] * ambient + sum(specular)
            lit = torch.where(default_material(surface["roughness"], surface["metallic"]), lit, pbr)
        return lit + surface["emission"] if self.plan.emission else lit

    def _rounded(self, o, d, s, hits: Hits):
        """Refine hits inside rounded voxels; rays that miss the rounded shape continue the DDA."""
        p, g, r = self.p, self.grid, self.p.rounded
        hit, t, cell, axis, mat = hits.hit.clone(), hits.t.clone(), hits.cell.clone(), hits.axis.clone(), hits.material.clone()
        normal = torch.zeros_like(o)
        extra = torch.zeros_like(hits.steps)
        pending = hit.nonzero().squeeze(1)
        hit[:] = False
        for attempt in range(r.retries + 1):
            if not pending.numel():
                break
            sp, dp, tp, cp = s[pending], d[pending], t[pending], cell[pending]
            size = g.voxel_size[sp]
            local = g.to_grid(o[pending] + tp[:, None] * dp, sp) - cp.to(o.dtype) - 0.5
            ok, adv, nrm = rounded_refine(local, dp, cp, radius_min=take(r.radius_min, sp), radius_range=take(r.radius_range, sp),
                                          steps=r.steps, threshold=take(r.threshold, sp), seed=r.seed)
            extra[pending] += r.steps
            good = pending[ok]
            hit[good] = True
            t[good] = tp[ok] + adv[ok] * size[ok]
            normal[good] = nrm[ok]
            miss = pending[~ok]
            if not miss.numel() or attempt == r.retries:
                break
            # continue past this voxel: restart just after its exit
            og, dg = g.to_grid(o[miss], s[miss]), d[miss] / g.voxel_size[s[miss], None]
            c = cell[miss]
            far = torch.where(dg > 0, c + 1, c).to(o.dtype)
            zero = dg == 0
            tx = torch.where(zero, torch.full_like(far, torch.inf), (far - og) / torch.where(zero, torch.ones_like(far), dg))
            t_exit = tx.min(dim=1).values
            h2 = self._traverse(o[miss], d[miss], s[miss], max_steps=p.max_steps, t_min=t_exit, plain=True)
            # the restart must not re-enter the voxel it left (it starts just after t_exit)
            extra[miss] += h2.steps
            cell[miss], axis[miss], t[miss], mat[miss] = h2.cell, h2.axis, h2.t, h2.material
            pending = miss[h2.hit]
        return hit, t, cell, axis, mat, normal, extra
