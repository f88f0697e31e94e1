"""The voxel surface pass of a render: a batch's voxel grids and the per-chunk pipeline
(traversal, variants, shading, AO, shadow rays, fog, glow) assembled from dda/shade/grid.

`VoxelSurface.run(o, d, s, background, section)` returns, per ray [n]: ``hit``, ``t`` (world
distance of the first hit, inf for misses), ``color`` [n, 3] (what the ray sees behind any volume:
the shaded surface where hit, else `background`, with fog and glow applied), ``steps`` and the AOVs
the plan calls for (``normal`` [n, 3], ``uv`` [n, 2], ``material``, ``ao``, ``shadow``,
``roughness``, ``metallic``, ``water`` and ``water_floor_distance`` [n, 1]). With `voxels.water` a
ray that reaches the water plane first is a hit there: its colour mixes a reflected and a refracted
ray (water.py).

GGX materials (`ggx.py`) shade the sun and, with `voxels.reflections`, add a mirror reflection
ray traced through the same DDA and shaded the same way (AO, shadows, GGX; not the rounded, glow
or fog variants), the sky where it misses, weighted by F · (1 − roughness)²: rough surfaces use the
mirror direction faded out, not a sampled lobe (an approximation). Default materials (roughness 1,
metallic 0) stay Lambert, bit for bit.
`voxels.gi` replaces the ambient with path-traced bounces (`_gi`) or, with `method = "cone"`, with
cones through a mip chain of the grids' opacity and reflected light (`_cone`, `cone.py`).
Every per-scene value arrives as a (B, ...) tensor of the batch's `Stacked` voxels, or is handled
scene by scene (occupancy, texture atlas, the glow's SDF).
"""

from __future__ import annotations

from contextlib import nullcontext
from typing import Callable, Mapping, Sequence

import torch
from torch import Tensor

from ..geometry import sdf
from ..schema.batch import Stacked, per_scene, take
from ..light.lights import LightSource
from ..ops.mathops import take_rows
from .cone import OFFSET, build_mips, cone_directions, default_aperture, face_cells, trace_cones
from .dda import Hits, hybrid_traverse, traverse
from .fog import FogWalk, extinction
from .gi import bounce_uniforms, cosine_directions, lod_counts, lod_keys, path_keys
from .ggx import f0_of, f_schlick, ggx_reflect
from .grid import VoxelGrid
from .materials import VOXEL_MATERIALS, default_material, material_table
from .shade import atlas_sample, face_normal, face_tone, face_uv, rounded_refine, voxel_ao
from .walk import fused_traverse
from .water import beer, fresnel, plane_hit, reflect, refract, wave_normal

__all__ = ["VoxelSurface"]

SURFACE_AOVS = ("normal", "uv", "material", "ao", "shadow", "roughness", "metallic", "water", "water_floor_distance")
REFLECTION_OFFSET = 1e-3  # the seed's hitPos + normal · 0.001, in voxels


class VoxelSurface:
    """One batch's voxel grids and shading parameters (`voxels`: the batch's `Stacked` voxels),
    lit by `lights`; `plan` the batch's `VoxelPass`; `aovs` the AOVs to output, name -> channels; `time` (B,) the
    scenes' times (water waves); `sky(directions [n, 3], s [n]) -> [n, 3]` what secondary rays that
    leave the grid see (None: black)."""

    def __init__(self, voxels: Stacked, lights: Sequence[LightSource], plan, aovs: Mapping[str, int], *, dtype, device,
                 compiled: bool = False, time: Tensor | None = None, sky: Callable[[Tensor, Tensor], Tensor] | None = None):
        # sky(directions [n, 3], scenes [n]) -> radiance [n, 3]: what secondary rays (water, GI paths) that leave the grid see
        self.p, self.lights, self.plan, self.compiled = voxels, list(lights), plan, compiled
        self.time, self.sky = time, sky
        self.grid = VoxelGrid.from_specs(voxels.models, dtype=dtype, device=device, with_distance=plan.traversal == "hybrid")
        self.aov_channels = {a: c for a, c in aovs.items() if a in SURFACE_AOVS}
        self.material = VOXEL_MATERIALS["diffuse"]
        self.materials = material_table(voxels.materials)  # (B, M, ...)
        if plan.texture:
            self.atlases = [torch.as_tensor(a, device=device) for a in voxels.texture.atlas]
        self.steps_total = 0
        self.mips = None  # the cone tracer's mip chain, built by the first chunk that needs it

    # -- helpers ---------------------------------------------------------------------------------

    def _traverse(self, o: Tensor, d: Tensor, s: Tensor, *, max_steps: int, t_min=None, t_max=None, visit=None,
                  fog: FogWalk | None = None, plain=False) -> Hits:
        """World rays [n, 3] of scenes s [n] through their grids (t in world units)."""
        g = self.grid
        og, dg = g.to_grid(o, s), d / g.voxel_size[s, None]
        lookup = lambda c, ids: g.lookup(c, take_rows(s, ids))
        lo, hi = take_rows(g.lo, s), take_rows(g.hi, s)
        hybrid = self.plan.traversal == "hybrid" and visit is None and fog is None and not plain
        if self.compiled:
            base, strides = g.flat_base(s)
            return fused_traverse(og, dg, g.flat_materials, base, strides, lo, hi, max_steps=max_steps,
                                  t_min=t_min, t_max=t_max, visit=visit, fog=fog,
                                  distance=g.flat_distance if hybrid else None)
        if hybrid:
            return hybrid_traverse(og, dg, lookup, lambda c, ids: g.empty_radius(c, take_rows(s, ids)), lo, hi,
                                   max_steps=max_steps, t_min=t_min)
        return traverse(og, dg, lookup, lo, hi, max_steps=max_steps, t_min=t_min, t_max=t_max, visit=visit)

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
        """The per-cell callback of the DDA when glow or fog accumulate, its accumulators and, with
        fog, `finish()`, which adds the fog's in-scattered light after the traversal (`_fog_light`).
        Fog alone on the compiled walk is accumulated inside the walk's kernel instead (the
        `FogWalk` returned last; the callback is then None)."""
        p, g, n, dt = self.p, self.grid, o.shape[0], o.dtype
        acc = dict(glow=o.new_zeros(n), fog_tau=o.new_zeros(n), fog_light=o.new_zeros(n, 3))
        visits = []  # (ray ids [m], scenes [m], cells [m, 3], weights [m]) of the fog's visited empty cells
        walked = None
        if self.compiled and self.plan.fog and not self.plan.glow:
            walked = self._fog_walk(s)

        def visit(ids, cells, t_in, t_out, hit):
            sc = take_rows(s, ids)
            if self.plan.glow:  # the seed's sdSomeShape(vec3(mapPos)): the cell corner, each scene's own SDF
                corner = g.to_world(cells.to(dt), sc)
                dist = per_scene(corner, sc, len(p), lambda b, _, q: sdf.evaluate(p.occupancy[b].sdf.shape, q))
                acc["glow"].index_add_(0, ids, take(p.glow.intensity, sc) / (take(p.glow.epsilon, sc) + dist * dist))
            if self.plan.fog:
                e = (~hit).nonzero().squeeze(1)
                if e.numel():
                    ie, se, ce = take_rows(ids, e), take_rows(sc, e), take_rows(cells, e)
                    centre = g.to_world(ce.to(dt) + 0.5, se)
                    f = p.fog
                    sigma = extinction(centre[:, 1], take(f.density, se), take(f.base, se), take(f.scale_height, se))
                    tau = sigma * (take_rows(t_out, e) - take_rows(t_in, e)).clamp_min(0.0)
                    acc["fog_tau"].index_add_(0, ie, tau)
                    visits.append((ie, se, ce, tau * torch.exp(-take_rows(acc["fog_tau"], ie))))

        def finish():
            if walked is not None:
                acc["fog_tau"] = walked.tau
                visits.extend((ie, take_rows(s, ie), ce, weight) for ie, ce, weight in walked.visits)
            for ie, se, light in self._fog_light(visits):
                acc["fog_light"].index_add_(0, ie, light * take(p.fog.color, se))

        return (visit if walked is None else None), acc, finish, walked

    def _fog_walk(self, s: Tensor) -> FogWalk:
        """The fog of rays of scenes s [n] as the fused walk takes it: σ at the centre of every row
        of cells of every scene, computed here as the callback computes it at a cell."""
        g, f = self.grid, self.p.fog
        B, Y = g.materials.shape[0], g.materials.shape[2]
        scenes = torch.arange(B, device=s.device)
        cy = g.lo[:, 1:2] + torch.arange(Y, device=s.device)  # (B, Y)
        y = g.origin[:, 1:2] + (cy.to(g.origin.dtype) + 0.5) * g.voxel_size[:, None]  # `to_world`'s sum
        sigma = extinction(y, *(take(v, scenes)[:, None] for v in (f.density, f.base, f.scale_height)))
        return FogWalk(rows=s * Y - take_rows(g.lo[:, 1], s), table=sigma.reshape(-1))

    def _fog_light(self, visits: list) -> list:
        """The light [m, 3] each fog visit (ray ids, scenes, cells, weights as `visit` recorded them)
        scatters towards its ray: weight · Σ lights' irradiance · visibility at the cell centre. The
        light at a centre depends on its cell alone, so one shadow ray per distinct visited cell
        (`fog_light_reference`: one per visit) gives the same bits at a tenth of the rays."""
        if not visits:
            return []
        g = self.grid
        key = g.cell_index(torch.cat([v[2] for v in visits]), torch.cat([v[1] for v in visits]))
        # the distinct keys in ascending order and each visit's rank among them, from one mark per
        # grid cell (a table the grid's own size): linear, where sorting the visits (torch.unique) is not
        seen = torch.zeros(g.materials.numel(), dtype=torch.bool, device=key.device).index_fill_(0, key, True)
        unique = seen.nonzero().squeeze(1)
        rank = torch.empty(seen.shape[0], dtype=torch.long, device=key.device)
        inverse = take_rows(rank.index_copy_(0, unique, torch.arange(unique.shape[0], device=key.device)), key)
        light = take_rows(self._fog_irradiance(*g.index_cell(unique)), inverse)
        out, start = [], 0
        for ie, se, _, weight in visits:
            out.append((ie, se, weight[:, None] * light[start:start + ie.shape[0]]))
            start += ie.shape[0]
        return out

    def fog_light_reference(self, visits: list) -> list:
        """`_fog_light` with a shadow ray per visit: the slow, obvious twin."""
        return [(ie, se, weight[:, None] * self._fog_irradiance(ce, se)) for ie, se, ce, weight in visits]

    def _fog_irradiance(self, cells: Tensor, s: Tensor) -> Tensor:
        """Σ lights' irradiance [m, 3] reaching the centres of cells [m, 3] of scenes s [m], each
        shadowed by a `fog.shadow_steps` DDA ray."""
        centre = self.grid.to_world(cells.to(self.grid.origin.dtype) + 0.5, s)
        light = centre.new_zeros(centre.shape[0], 3)
        for source in self.lights:
            toward = source.toward(centre, s)
            vis = self._visibility(centre, s, source, self.p.fog.shadow_steps, toward)
            light = light + toward.irradiance * vis[:, None]
        return light

    # -- the pass --------------------------------------------------------------------------------

    def run(self, o: Tensor, d: Tensor, s: Tensor, background: Tensor,
            section: Callable[[str], object] = lambda name: nullcontext(), keys: Tensor | None = None) -> dict[str, Tensor]:
        """o, d [n, 3] world rays (d unit); s [n] scenes; background [n, 3]; keys [n, 3] long: each
        ray's (sub-pixel column, row, scene seed), the hash cells of its GI paths (needed with `voxels.gi`)."""
        p, n = self.p, o.shape[0]
        visit, acc, finish, walked = self._glow_and_fog(o, s) if self.plan.glow or self.plan.fog else (None,) * 4
        with section("voxels.dda"):
            hits = self._traverse(o, d, s, max_steps=p.max_steps, visit=visit, fog=walked)
        if self.plan.fog:
            with section("voxels.fog"):
                finish()
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
        aovs = {k: o.new_zeros(n, c) for k, c in self.aov_channels.items()}
        if ids.numel():
            sh = take_rows(s, ids)
            with section("voxels.shade"):
                surface = self._surface(*(take_rows(x, ids) for x in (o, d, t, cell, axis, mat)), sh,
                                        None if normal_override is None else take_rows(normal_override, ids))
            self._ao(surface, sh, section)
            indirect = None
            if self.plan.cone:
                indirect = self._cone(surface, sh, t[ids], section)
            elif self.plan.gi:
                with section("voxels.gi"):
                    indirect = self._gi(surface, sh, keys[ids], t[ids])
            out_color[ids] = self._lit(surface, sh, section, indirect)
            if self.plan.reflections:
                with section("voxels.reflections"):
                    self._reflect(out_color, ids, surface, d[ids], sh, self.plan.reflections, section)
            for k in self.aov_channels:
                if k in surface:  # the water's AOVs come from _water
                    aovs[k][ids] = surface[k]
        if self.plan.fog:
            out_color = out_color * torch.exp(-acc["fog_tau"])[:, None] + acc["fog_light"]
        if self.plan.glow:
            out_color = out_color + acc["glow"][:, None] * take(p.glow.color, s)
        t_hit = torch.where(hit, t, torch.full_like(t, torch.inf))
        if self.plan.water:
            hit, t_hit, out_color = self._water(o, d, s, t_hit, out_color, aovs, section)
        return dict(hit=hit, t=t_hit, color=out_color, steps=steps, aovs=aovs)

    def _water(self, o, d, s, t_hit, color, aovs, section):
        """Rays o, d [n, 3] of scenes s [n] whose surface hit is at t_hit [n] (inf: none) and colour
        [n, 3] through the water plane -> (hit, t, colour): a ray that reaches the plane first
        stops there, its colour the Fresnel mix of a reflected and a refracted ray (total internal
        reflection from below); paths under water are attenuated by Beer-Lambert."""
        w = self.p.water
        level, absorb = take(w.level, s), take(w.absorption, s)
        under = o[:, 1] < level  # the camera is in the water: its whole primary path is
        t_water = plane_hit(o, d, level)
        # a camera exactly on the plane looking down enters the water where it stands (the limit from above)
        t_water = torch.where((o[:, 1] == level) & (d[:, 1] < 0), torch.zeros_like(t_water), t_water)
        on = t_water < t_hit
        color = torch.where((under & ~on)[:, None], color * beer(absorb, t_hit), color)
        if "water" in aovs:
            aovs["water"] = on.to(o.dtype)[:, None]
        ids = on.nonzero().squeeze(1)
        if not ids.numel():  # no ray met the water: the pass did not run
            return t_hit < torch.inf, t_hit, color
        with section("voxels.water"):
            return self._on_water(o, d, s, ids, on, t_water, t_hit, under, color, aovs, section)

    def _on_water(self, o, d, s, ids, on, t_water, t_hit, under, color, aovs, section):
        """`_water` for the rays ids [m] that meet the water (`on` [n]) at t_water [n]."""
        w = self.p.water
        level, absorb = take(w.level, s), take(w.absorption, s)
        di, si, ui, tw = d[ids], s[ids], under[ids], t_water[ids]
        x = o[ids] + tw[:, None] * di
        x[:, 1] = level[ids]  # exactly on the plane
        up = wave_normal(x, take(w.waves.amplitude, si), take(w.waves.frequency, si), take(w.waves.speed, si),
                         take(self.time, si))
        flat = torch.zeros_like(up)
        flat[:, 1] = 1.0
        sign = torch.where(ui, -1.0, 1.0).to(x.dtype)[:, None]  # the normal on the ray's side
        n = up * sign
        # a grazing ray can meet the back of a tilted wave normal: it sees the flat plane there
        n = torch.where(((di * n).sum(1) >= 0)[:, None], flat * sign, n)
        cos_i = (-(di * n).sum(1)).clamp(0.0, 1.0)
        ior = take(w.ior, si)
        eta = torch.where(ui, ior, 1.0 / ior)
        f = fresnel(cos_i, eta, w.fresnel)
        refr, tir = refract(di, n, eta)
        off = take(w.offset, si)[:, None] * n
        a = absorb[ids]
        # the reflected ray stays on the ray's side (in water from below), the refracted one crosses
        refl_col, refl_len = self._trace_shade(x + off, reflect(di, n), si, section, max_steps=self.p.max_steps)
        refl_col = torch.where(ui[:, None], refl_col * beer(a, refl_len), refl_col)
        refr_col = torch.zeros_like(refl_col)
        floor = torch.full_like(tw, torch.inf)
        k = (~tir).nonzero().squeeze(1)
        if k.numel():
            col, length = self._trace_shade(x[k] - off[k], refr[k], si[k], section, max_steps=self.p.max_steps)
            refr_col[k] = torch.where(ui[k, None], col, col * beer(a[k], length))
            floor[k] = torch.where(ui[k], floor[k], length)
        mixed = f[:, None] * refl_col + (1.0 - f)[:, None] * refr_col
        color[ids] = torch.where(ui[:, None], mixed * beer(a, tw), mixed)
        if "water_floor_distance" in aovs:
            seen = floor < torch.inf
            aovs["water_floor_distance"][ids] = torch.where(
                seen, torch.linalg.vector_norm(x + floor[:, None] * refr - o[ids], dim=1), torch.zeros_like(tw))[:, None]
        for key in ("normal", "uv", "material", "ao", "shadow"):  # the water's hit, not the voxel's behind it
            if key in aovs:
                aovs[key][ids] = up * sign if key == "normal" else 0.0
        t_hit = torch.where(on, t_water, t_hit)
        return t_hit < torch.inf, t_hit, color

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
        color[ids[live]] += weight[live] * self._trace_shade(start, r, sl, section, max_steps=self.p.reflections.steps,
                                                             bounces=bounces)[0]

    def _trace_shade(self, o: Tensor, d: Tensor, s: Tensor, section, *, max_steps: int,
                     bounces: int = 0) -> tuple[Tensor, Tensor]:
        """A secondary ray (off the water, or a reflection) o, d [n, 3] (d unit) of scenes s [n]
        through the voxels, its hit lit like a primary one (AO, shadows, materials; its own
        reflection while `bounces` > 1 remain), the sky where it leaves -> (colour [n, 3], hit
        distance [n], inf: none)."""
        h = self._traverse(o, d, s, max_steps=max_steps, plain=True)
        self.steps_total += int(h.steps.sum())
        color = o.new_zeros(o.shape[0], 3) if self.sky is None else self.sky(d, s).clone()  # a sky may be expanded
        ids = h.hit.nonzero().squeeze(1)
        if ids.numel():
            sh = s[ids]
            surface = self._surface(o[ids], d[ids], h.t[ids], h.cell[ids], h.axis[ids], h.material[ids], sh, None)
            self._ao(surface, sh, section)
            color[ids] = self._lit(surface, sh, section)
            if bounces > 1:
                self._reflect(color, ids, surface, d[ids], sh, bounces - 1, section)
        return color, torch.where(h.hit, h.t, torch.full_like(h.t, torch.inf))

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

    def _lit(self, surface: dict[str, Tensor], s: Tensor, section, indirect: Tensor | None = None) -> Tensor:
        """Ambient (or the GI's `indirect` incoming radiance [n, 3]) plus each light's irradiance,
        shadowed by a DDA ray where `voxels.shadow` is set; GGX materials reflect each light by
        `ggx_reflect` (ambient and indirect light stay diffuse: albedo · ambient)."""
        ambient = take(self.p.ambient, s) if indirect is None else indirect
        light, specular = self._direct(surface, s, section, ambient)
        lit = surface["albedo"] * light
        if self.plan.ggx:
            pbr = surface["albedo"] * ambient + specular
            lit = torch.where(default_material(surface["roughness"], surface["metallic"]), lit, pbr)
        return lit + surface["emission"] if self.plan.emission else lit

    def _direct(self, surface: dict[str, Tensor], s: Tensor, section, light: Tensor) -> tuple[Tensor, Tensor | int]:
        """`light` [n, 3] plus the lights' Lambert irradiance per unit albedo at surface points
        (summed in this order: renders without GI are bitwise as before), and the lights' GGX
        reflected radiance [n, 3] (0 without GGX)."""
        p, specular = self.p, 0
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
                specular = specular + (ggx_reflect(surface["normal"], surface["view"], toward.direction, surface["albedo"],
                                                   surface["roughness"][:, 0], surface["metallic"][:, 0])
                                       * toward.irradiance * vis[:, None])
        return light, specular

    def _gi(self, surface: dict[str, Tensor], s: Tensor, keys: Tensor, distance: Tensor) -> Tensor:
        """The mean incoming radiance [n, 3] of `voxels.gi`'s paths from the hits `surface`
        (scenes s [n], hash keys [n, 3], camera distance [n]): cosine-weighted, so the estimate is
        the plain path mean."""
        gi, n = self.p.gi, s.shape[0]
        S = gi.samples
        if gi.lod is None:
            cells, owner = path_keys(keys, S), None
            ps = s.repeat_interleave(S)
            x, normal = surface["x"].repeat_interleave(S, dim=0), surface["face_normal"].repeat_interleave(S, dim=0)
        else:
            counts = lod_counts(distance, S, take(gi.lod.near, s), take(gi.lod.far, s), gi.lod.samples)
            cells, owner = lod_keys(keys, counts, S)
            ps, x, normal = s[owner], surface["x"][owner], surface["face_normal"][owner]
        radiance, throughput = torch.zeros_like(x), torch.ones_like(x)
        alive = torch.arange(x.shape[0], device=x.device)
        # start a thousandth of a voxel off the face so the DDA starts in the empty cell in front of it
        eps = 1e-3 * self.grid.voxel_size
        for bounce in range(gi.bounces):
            sa = ps[alive]
            d = cosine_directions(normal, *bounce_uniforms(cells[alive], bounce, x.dtype))
            o = x + eps[sa, None] * normal
            h = self._traverse(o, d, sa, max_steps=self.p.max_steps, plain=True)
            self.steps_total += int(h.steps.sum())
            if self.sky is not None:
                miss = (~h.hit).nonzero().squeeze(1)
                radiance.index_add_(0, alive[miss], throughput[alive[miss]] * self.sky(d[miss], sa[miss]))
            keep = h.hit.nonzero().squeeze(1)
            alive, sa = alive[keep], sa[keep]
            if not alive.numel():
                break
            hit = self._surface(o[keep], d[keep], h.t[keep], h.cell[keep], h.axis[keep], h.material[keep], sa, None)
            incoming, _ = self._direct(hit, sa, lambda name: nullcontext(), torch.zeros_like(hit["x"]))  # paths see diffuse light
            own = hit["albedo"] * incoming
            if self.plan.emission:
                own = own + hit["emission"]
            radiance.index_add_(0, alive, throughput[alive] * own)
            throughput[alive] = throughput[alive] * hit["albedo"]
            x, normal = hit["x"], hit["face_normal"]
        if owner is None:
            return radiance.view(n, S, 3).mean(dim=1)
        return torch.zeros_like(surface["x"]).index_add_(0, owner, radiance) / counts[:, None].to(radiance.dtype)

    def _cone_mips(self) -> list[Tensor]:
        """The mip chain (`cone.build_mips`) of the batch's grids: each cell's radiance the mean over
        its exposed faces of what a path-traced bounce sees there (albedo · direct light + emission,
        shaded by `_surface` and `_direct` at the face centre)."""
        g = self.grid
        occupied = g.materials > 0
        B, Z, Y, X = occupied.shape
        dt = g.origin.dtype
        faces = [(b, axis, sign, idx) for b in range(B) for axis, sign, idx in face_cells(occupied[b]) if idx.numel()]
        radiance = g.origin.new_zeros(B * Z * Y * X, 3)
        count = g.origin.new_zeros(B * Z * Y * X)
        if faces:
            idx = torch.cat([f[3] for f in faces])
            s = torch.cat([torch.full((f[3].shape[0],), f[0], dtype=torch.long, device=idx.device) for f in faces])
            axis = torch.cat([torch.full((f[3].shape[0],), f[1], dtype=torch.long, device=idx.device) for f in faces])
            outward = g.origin.new_zeros(idx.shape[0], 3)
            outward[torch.arange(idx.shape[0]), axis] = torch.cat([torch.full((f[3].shape[0],), float(f[2]), dtype=dt)
                                                                   for f in faces])
            cell = idx + g.lo[s]
            flat = ((s * Z + idx[:, 2]) * Y + idx[:, 1]) * X + idx[:, 0]
            # a ray from one voxel out, straight onto the face's centre
            x = g.to_world(cell.to(dt) + 0.5 + 0.5 * outward, s)
            size = g.voxel_size[s]
            hit = self._surface(x + size[:, None] * outward, -outward, size, cell, axis,
                                g.materials.reshape(-1)[flat].long(), s, None)
            incoming, _ = self._direct(hit, s, lambda name: nullcontext(), torch.zeros_like(x))
            own = hit["albedo"] * incoming + (hit["emission"] if self.plan.emission else 0.0)
            radiance.index_add_(0, flat, own)
            count.index_add_(0, flat, torch.ones_like(flat, dtype=dt))
        radiance = (radiance / count.clamp_min(1.0)[:, None]).view(B, Z, Y, X, 3).permute(0, 4, 1, 2, 3)
        return build_mips(occupied.to(dt), radiance, (count > 0).to(dt).view(B, Z, Y, X))

    def _cone(self, surface: dict[str, Tensor], s: Tensor, distance: Tensor, section) -> Tensor:
        """The cones' incoming radiance [n, 3] at the hits `surface` of scenes s [n], seen from the
        camera at `distance` [n] (world units); with `ao` their visibility multiplies the albedo."""
        gi, g = self.p.gi, self.grid
        if self.mips is None:
            with section("voxels.gi.mips"):
                self.mips = self._cone_mips()
        with section("voxels.gi.cones"):
            n, dt = s.shape[0], surface["x"].dtype
            cones = gi.cones
            half = (torch.full((len(self.p),), default_aperture(cones), dtype=dt, device=s.device)
                    if gi.aperture is None else gi.aperture)
            half = take(half, s)
            groups = [(torch.arange(n, device=s.device), cones)]
            if gi.lod is not None:
                near, far = take(gi.lod.near, s), take(gi.lod.far, s)
                w = ((distance - near) / (far - near)).clamp(0.0, 1.0)
                half = half + w * (take(gi.lod.aperture, s) - half)
                beyond = distance >= far
                groups = [(h, k) for h, k in (((~beyond).nonzero().squeeze(1), cones),
                                              (beyond.nonzero().squeeze(1), gi.lod.cones)) if h.numel()]
            ratio = 2.0 * torch.tan(torch.deg2rad(half))
            owner = torch.cat([h.repeat_interleave(k) for h, k in groups])
            weight = torch.cat([torch.full((h.numel() * k,), 1.0 / k, dtype=dt, device=s.device) for h, k in groups])
            d = torch.cat([cone_directions(surface["face_normal"][h], k).reshape(-1, 3) for h, k in groups])
            so = s[owner]
            origin = g.to_grid(surface["x"][owner], so) - g.lo[so].to(dt) + OFFSET * surface["face_normal"][owner]
            color, occ = trace_cones(self.mips, origin, d, so, ratio[owner], steps=gi.steps,
                                     max_t=take(gi.max_distance, so) / g.voxel_size[so])
            if self.sky is not None:
                color = color + (1.0 - occ)[:, None] * self.sky(d, so)
            indirect = torch.zeros_like(surface["x"]).index_add_(0, owner, weight[:, None] * color)
            if gi.ao:
                ao = torch.zeros_like(distance).index_add_(0, owner, weight * (1.0 - occ))[:, None]
                surface["albedo"] = surface["albedo"] * ao
                surface["ao"] = surface["ao"] * ao if "ao" in surface else ao
        return indirect

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
