"""The variants gathered along a primary ray's DDA: `voxels.glow` (each visited cell adds the
seed's intensity / (ε + sdf²) at its corner, the scene's own SDF: one table of every cell's term,
`FogGlow.glow_table`, that the eager callback and the Dr.Jit walk both read) and `voxels.fog` (a height fog:
each visited empty cell's optical depth, and the light it scatters towards the ray, one shadow ray
per distinct visited cell). The fog's formula is `voxel/fog.py`'s."""

from __future__ import annotations

from functools import cached_property
from typing import Sequence

import torch
from torch import Tensor

from ...geometry import sdf
from ...light.lights import LightSource
from ...ops.mathops import take_rows
from ...schema.batch import Stacked, per_scene, take
from ..fog import FogWalk, GlowWalk, extinction
from ..tracer import VoxelTracer

__all__ = ["FogGlow", "FogGlowRays"]


class FogGlow:
    """The batch's fog and glow (`voxels`: its `Stacked` voxels; `plan` its `VoxelPass`) through
    `tracer`'s grids, lit by `lights`. `rays(o, s)` starts one chunk's accumulation."""

    def __init__(self, voxels: Stacked, plan, lights: Sequence[LightSource], tracer: VoxelTracer):
        self.p, self.plan, self.lights, self.tracer = voxels, plan, list(lights), tracer

    def rays(self, o: Tensor, s: Tensor) -> FogGlowRays:
        """The accumulators of primary rays from o [n, 3] of scenes s [n]."""
        return FogGlowRays(self, o, s)

    def fog_walk(self, s: Tensor) -> FogWalk:
        """The fog of rays of scenes s [n] as the Dr.Jit walk takes it: σ at the centre of every row
        of cells of every scene, computed here as the callback computes it at a cell."""
        g, f = self.tracer.grid, self.p.fog
        B, Y = g.materials.shape[0], g.materials.shape[2]
        scenes = torch.arange(B, device=s.device)
        cy = g.lo[:, 1:2] + torch.arange(Y, device=s.device)  # (B, Y)
        y = g.origin[:, 1:2] + (cy.to(g.origin.dtype) + 0.5) * g.voxel_size[:, None]  # `to_world`'s sum
        sigma = extinction(y, *(take(v, scenes)[:, None] for v in (f.density, f.base, f.scale_height)))
        return FogWalk(rows=s * Y - take_rows(g.lo[:, 1], s), table=sigma.reshape(-1), color=take(f.color, s),
                       irradiance=lambda flat: self._fog_irradiance(*g.index_cell(flat)))

    @cached_property
    def glow_table(self) -> Tensor:
        """The glow's term [M] of every cell of the flattened grids (`VoxelGrid.flat_materials`'s
        order): intensity / (ε + d²), d the scene's own SDF at the cell's corner (the seed's
        sdSomeShape(vec3(mapPos))); made once a render."""
        p, g = self.p, self.tracer.grid
        cells, sc = g.index_cell(torch.arange(g.materials.numel(), device=g.lo.device))
        corner = g.to_world(cells.to(g.origin.dtype), sc)
        dist = per_scene(corner, sc, len(p), lambda b, _, q: sdf.evaluate(p.occupancy[b].sdf.shape, q))
        return take(p.glow.intensity, sc) / (take(p.glow.epsilon, sc) + dist * dist)

    def _fog_light(self, visits: list) -> list:
        """The light [m, 3] each fog visit (ray ids, scenes, cells, weights as `visit` recorded them)
        scatters towards its ray: weight · Σ lights' irradiance · visibility at the cell centre. The
        light at a centre depends on its cell alone, so one shadow ray per distinct visited cell
        (`fog_light_reference`: one per visit) gives the same bits at a tenth of the rays."""
        if not visits:
            return []
        g = self.tracer.grid
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
        g = self.tracer.grid
        centre = g.to_world(cells.to(g.origin.dtype) + 0.5, s)
        light = centre.new_zeros(centre.shape[0], 3)
        for source in self.lights:
            toward = source.toward(centre, s)
            vis = self.tracer.visibility(centre, s, source, self.p.fog.shadow_steps, toward)
            light = light + toward.irradiance * vis[:, None]
        return light


class FogGlowRays:
    """What the glow and fog of `owner` gather along primary rays from o [n, 3] of scenes s [n]:
    `glow` [n], the fog's optical depth `fog_tau` [n] and in-scattered light `fog_light` [n, 3].
    The eager DDA calls `visit` per cell; the Dr.Jit walk accumulates them inside its kernel
    instead (`walked` and `glowed`, the `FogWalk` and `GlowWalk` to hand the walk; `visit` is then None)."""

    def __init__(self, owner: FogGlow, o: Tensor, s: Tensor):
        n = o.shape[0]
        self.owner, self.s, self.dtype = owner, s, o.dtype
        self.glow, self.fog_tau, self.fog_light = o.new_zeros(n), o.new_zeros(n), o.new_zeros(n, 3)
        self.visits = []  # (ray ids [m], scenes [m], cells [m, 3], weights [m]) of the fog's visited empty cells
        plan, drjit = owner.plan, owner.tracer.drjit
        self.walked = owner.fog_walk(s) if drjit and plan.fog else None
        self.glowed = GlowWalk(owner.glow_table) if drjit and plan.glow else None
        self.visit = None if drjit else self._visit

    def _visit(self, ids: Tensor, cells: Tensor, t_in: Tensor, t_out: Tensor, hit: Tensor) -> None:
        """The DDA's per-cell callback: rays ids [m] in cells [m, 3] from t_in to t_out [m], `hit` [m]
        where the cell is occupied."""
        p, g, plan = self.owner.p, self.owner.tracer.grid, self.owner.plan
        sc = take_rows(self.s, ids)
        if plan.glow:
            self.glow.index_add_(0, ids, take_rows(self.owner.glow_table, g.cell_index(cells, sc)))
        if plan.fog:
            e = (~hit).nonzero().squeeze(1)
            if e.numel():
                ie, se, ce = take_rows(ids, e), take_rows(sc, e), take_rows(cells, e)
                centre = g.to_world(ce.to(self.dtype) + 0.5, se)
                f = p.fog
                sigma = extinction(centre[:, 1], take(f.density, se), take(f.base, se), take(f.scale_height, se))
                tau = sigma * (take_rows(t_out, e) - take_rows(t_in, e)).clamp_min(0.0)
                self.fog_tau.index_add_(0, ie, tau)
                self.visits.append((ie, se, ce, tau * torch.exp(-take_rows(self.fog_tau, ie))))

    def finish(self) -> None:
        """After the traversal: the glow, the fog's τ and in-scattered light, as the Dr.Jit walk
        summed them or from the visits the eager walk recorded."""
        if self.glowed is not None:
            self.glow = self.glowed.total
        if self.walked is not None:
            self.fog_tau, self.fog_light = self.walked.tau, self.walked.light
            return
        for ie, se, light in self.owner._fog_light(self.visits):
            self.fog_light.index_add_(0, ie, light * take(self.owner.p.fog.color, se))

    def apply(self, color: Tensor) -> Tensor:
        """What the rays see [n, 3] of `color` [n, 3] behind the fog, plus the glow."""
        if self.owner.plan.fog:
            color = color * torch.exp(-self.fog_tau)[:, None] + self.fog_light
        if self.owner.plan.glow:
            color = color + self.glow[:, None] * take(self.owner.p.glow.color, self.s)
        return color
