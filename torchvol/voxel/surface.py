"""The voxel surface pass of a render: per-scene tensors of a batch's `voxels` sections and the
per-chunk pipeline (traversal, variants, shading, AO, shadow rays) assembled from dda/shade/grid.

`VoxelSurface.run(rays, background, section)` returns, per ray [n]: ``hit``, ``t`` (world distance
of the first hit, inf for misses), ``color`` [n, 3] (what the ray sees behind any volume: the shaded
surface where hit, else `background`, with fog and glow applied), ``steps`` and the AOVs the scene
calls for (``normal`` [n, 3], ``uv`` [n, 2], ``material``, ``ao``, ``shadow`` [n, 1]).
"""

from __future__ import annotations

from contextlib import nullcontext
from typing import Callable, Sequence

import torch
from torch import Tensor

from .. import sdf
from .dda import Hits, hybrid_traverse, traverse
from .grid import VoxelGrid
from .shade import atlas_sample, face_normal, face_tone, face_uv, lambert, rounded_refine, voxel_ao

__all__ = ["VoxelSurface", "surface_aovs"]


def surface_aovs(spec, n_lights: int) -> list[str]:
    """The AOV names a `voxels` section produces (only what is computed)."""
    names = ["normal", "uv"]
    if len(spec.materials) > 1 or spec.texture is not None:
        names.append("material")
    if spec.ao is not None:
        names.append("ao")
    if spec.shadow is not None and n_lights:
        names.append("shadow")
    return names


class VoxelSurface:
    """One batch's voxel grids and shading parameters. `sun_dir`, `sun_radiance` (L, B, 3)."""

    def __init__(self, specs: Sequence, sun_dir: Tensor, sun_radiance: Tensor, *, dtype, device, compiled: bool = False):
        self.specs, self.spec, self.compiled = specs, specs[0], compiled
        self.kw = dict(dtype=dtype, device=device)
        self.grid = VoxelGrid.from_specs(specs, dtype=dtype, device=device, with_distance=self.spec.traversal == "hybrid")
        self.sun_dir, self.sun_radiance = sun_dir, sun_radiance
        t = lambda v: torch.tensor(v, **self.kw)
        n_mat = max(len(s.materials) for s in specs)
        self.materials = t([list(s.materials) + [s.materials[-1]] * (n_mat - len(s.materials)) for s in specs])  # (B, M, 3)
        self.tones = t([s.face_tones for s in specs])
        self.ambient = t([s.ambient for s in specs])
        self.aov_names = surface_aovs(self.spec, sun_dir.shape[0])
        if self.spec.ao is not None:
            self.ao_gamma = t([s.ao.gamma for s in specs])
        if self.spec.texture is not None:
            self.atlases = [torch.as_tensor(s.texture.atlas, device=device) for s in specs]
        if self.spec.glow is not None:
            self.glow = {k: t([getattr(s.glow, k) for s in specs]) for k in ("intensity", "epsilon", "color")}
        if self.spec.fog is not None:
            self.fog = {k: t([getattr(s.fog, k) for s in specs]) for k in ("density", "base", "scale_height", "color")}
        self.steps_total = 0

    # -- helpers ---------------------------------------------------------------------------------

    def _traverse(self, o: Tensor, d: Tensor, s: Tensor, *, max_steps: int, t_min=None, visit=None, plain=False) -> Hits:
        """World rays [n, 3] of scenes s [n] through their grids (t in world units)."""
        g = self.grid
        og, dg = g.to_grid(o, s), d / g.voxel_size[s, None]
        lookup = lambda c, ids: g.lookup(c, s[ids])
        lo, hi = g.lo[s], g.hi[s]
        if self.spec.traversal == "hybrid" and visit is None and not plain:
            return hybrid_traverse(og, dg, lookup, lambda c, ids: g.empty_radius(c, s[ids]), lo, hi,
                                   max_steps=max_steps, t_min=t_min, compiled=self.compiled)
        return traverse(og, dg, lookup, lo, hi, max_steps=max_steps, t_min=t_min, visit=visit, compiled=self.compiled)

    def _shadow(self, p: Tensor, sun: Tensor, s: Tensor, steps: int) -> Tensor:
        """Visibility [n] (1 lit, 0 occluded) of points p [n, 3] towards sun [n, 3]."""
        if p.shape[0] == 0:
            return p.new_zeros(0)
        h = self._traverse(p, sun, s, max_steps=steps, plain=True)
        return (~h.hit).to(p.dtype)

    # -- the pass --------------------------------------------------------------------------------

    def run(self, o: Tensor, d: Tensor, s: Tensor, forward_cos: Tensor, background: Tensor,
            section: Callable[[str], object] = lambda name: nullcontext()) -> dict[str, Tensor]:
        """o, d [n, 3] world rays (d unit); s [n] scenes; forward_cos [n]; background [n, 3]."""
        spec, g, n = self.spec, self.grid, o.shape[0]
        dt = o.dtype
        glow, fog_tau, fog_light = None, None, None
        visit = None  # a per-cell callback only when glow or fog accumulate
        if spec.glow is not None or spec.fog is not None:
            glow = o.new_zeros(n)
            fog_tau, fog_light = o.new_zeros(n), o.new_zeros(n, 3)

            def visit(ids, cells, t_in, t_out, hit):
                sc = s[ids]
                if spec.glow is not None:  # the seed's sdSomeShape(vec3(mapPos)): the cell corner
                    dist = sdf.evaluate(spec.occupancy.sdf.shape, g.to_world(cells.to(dt), sc))
                    glow.index_add_(0, ids, self.glow["intensity"][sc] / (self.glow["epsilon"][sc] + dist * dist))
                if spec.fog is not None:
                    e = (~hit).nonzero().squeeze(1)
                    if e.numel():
                        ie, se = ids[e], sc[e]
                        centre = g.to_world(cells[e].to(dt) + 0.5, se)
                        f = self.fog
                        sigma = f["density"][se] * torch.exp(-(centre[:, 1] - f["base"][se]) / f["scale_height"][se])
                        tau = sigma * (t_out[e] - t_in[e]).clamp_min(0.0)
                        fog_tau.index_add_(0, ie, tau)
                        light = o.new_zeros(e.numel(), 3)
                        for li in range(self.sun_dir.shape[0]):
                            vis = self._shadow(centre, self.sun_dir[li][se], se, spec.fog.shadow_steps)
                            light = light + self.sun_radiance[li][se] * vis[:, None]
                        fog_light.index_add_(0, ie, (tau * torch.exp(-fog_tau[ie]))[:, None] * light * f["color"][se])

        with section("voxels.dda"):
            hits = self._traverse(o, d, s, max_steps=spec.max_steps, visit=visit)
        steps = hits.steps.clone()
        hit, t, cell, axis, mat = hits.hit, hits.t, hits.cell, hits.axis, hits.material
        normal_override = None
        if spec.rounded is not None:
            with section("voxels.rounded"):
                hit, t, cell, axis, mat, normal_override, extra = self._rounded(o, d, s, hits)
                steps = steps + extra
        self.steps_total += int(steps.sum())

        ids = hit.nonzero().squeeze(1)
        out_color = background.clone()
        aovs = {k: o.new_zeros(n, c) for k, c in (("normal", 3), ("uv", 2), ("material", 1), ("ao", 1), ("shadow", 1)) if k in self.aov_names}
        if ids.numel():
            with section("voxels.shade"):
                sh, dh, th, ch, ah = s[ids], d[ids], t[ids], cell[ids], axis[ids]
                p = o[ids] + th[:, None] * dh
                local = (g.to_grid(p, sh) - ch.to(dt)).clamp(0.0, 1.0)
                face_n = face_normal(ah, dh)
                normal = face_n if normal_override is None else normal_override[ids]
                uv = face_uv(local, ah)
                m = mat[ids]
                albedo = self.materials[sh, (m - 1).clamp(0, self.materials.shape[1] - 1)]
                if spec.texture is not None:
                    tex = torch.empty_like(albedo)
                    for b, atlas in enumerate(self.atlases):  # one atlas per scene: group the rays
                        k = (sh == b).nonzero().squeeze(1)
                        if k.numel():
                            tex[k] = atlas_sample(atlas, spec.texture.tiles, m[k], uv[k])
                    albedo = albedo * tex
                base = albedo * face_tone(ah, self.tones[sh])[:, None]
            ao = None
            if spec.ao is not None:
                with section("voxels.ao"):
                    ao = voxel_ao(lambda c: (g.lookup(c, sh.repeat(8)) > 0), ch, face_n, ah, uv, gamma=self.ao_gamma[sh])
                    base = base * ao[:, None]
            light = self.ambient[sh].clone()
            shadow0 = None
            for li in range(self.sun_dir.shape[0]):
                sun = self.sun_dir[li][sh]
                vis = torch.ones_like(th)
                if spec.shadow is not None:
                    with section(f"voxels.shadow{li}"):
                        vis = self._shadow(p + spec.shadow.offset * face_n, sun, sh, spec.shadow.steps)
                    shadow0 = vis if shadow0 is None else shadow0
                light = light + self.sun_radiance[li][sh] * (lambert(normal, sun) * vis)[:, None]
            out_color[ids] = base * light
            for k, v in (("normal", normal), ("uv", uv), ("material", m.to(dt)[:, None]),
                         ("ao", None if ao is None else ao[:, None]), ("shadow", None if shadow0 is None else shadow0[:, None])):
                if k in aovs and v is not None:
                    aovs[k][ids] = v
        if fog_tau is not None and spec.fog is not None:
            out_color = out_color * torch.exp(-fog_tau)[:, None] + fog_light
        if spec.glow is not None:
            out_color = out_color + glow[:, None] * self.glow["color"][s]
        t_hit = torch.where(hit, t, torch.full_like(t, torch.inf))
        return dict(hit=hit, t=t_hit, color=out_color, depth=torch.where(hit, t * forward_cos, torch.zeros_like(t)),
                    steps=steps, aovs=aovs)

    def _rounded(self, o, d, s, hits: Hits):
        """Refine hits inside rounded voxels; rays that miss the rounded shape continue the DDA."""
        spec, g, r = self.spec, self.grid, self.spec.rounded
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
            ok, adv, nrm = rounded_refine(local, dp, cp, radius_min=r.radius_min, radius_range=r.radius_range,
                                          steps=r.steps, threshold=r.threshold, seed=r.seed)
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
            h2 = self._traverse(o[miss], d[miss], s[miss], max_steps=spec.max_steps, t_min=t_exit, plain=True)
            # the restart must not re-enter the voxel it left (it starts just after t_exit)
            extra[miss] += h2.steps
            cell[miss], axis[miss], t[miss], mat[miss] = h2.cell, h2.axis, h2.t, h2.material
            pending = miss[h2.hit]
        return hit, t, cell, axis, mat, normal, extra
