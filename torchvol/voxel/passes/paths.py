"""`voxels.gi`'s path-traced bounces (the default method): from each hit, cosine-weighted paths
through the DDA, each bounce lit by the direct light (diffuse) and the sky where a path leaves the
grid; their mean replaces the ambient. A path is written once in lanes (`path_lanes`, the look's
point and direct light, `walk.cube_walk`): one Dr.Jit kernel over a chunk's paths where the walks
are kernels, else on torch columns (the reference). The keys, uniforms and LOD are `gi.py`'s."""

from __future__ import annotations

import math
from contextlib import nullcontext
from types import SimpleNamespace
from typing import Callable

import torch
from torch import Tensor

from ...noise.lattice import int32_bits
from ...ops import lanes
from ...runtime.compilation import traced_columns
from ...schema.batch import Stacked, take
from ..gi import (
    bounce_direction_lanes,
    bounce_uniform_lanes,
    lod_counts,
    lod_keys,
    path_keys,
)
from ..tracer import VoxelTracer
from ..walk import cube_walk
from .direct import DirectLight
from .look import direct_lanes, look_inputs, point_lanes_of, visible_beside
from .point import ShadingPoint
from .shading import Shading

__all__ = ["PathGI", "path_lanes"]


def path_lanes(q: SimpleNamespace, x: list, normal: list, cells: list, eps, *, bounces: int, visible, shadowed: dict,
               emission: bool, escapes: bool) -> SimpleNamespace:
    """Paths of `bounces` diffuse bounces from points `x` off faces of unit `normal` (three lanes
    each; `q`: `look.look_inputs` with the walks, `cells`: each path's hash cell, three int32 lanes),
    each starting `eps` (a lane) off its face: a bounce's direction from `gi.bounce_uniform_lanes`,
    its walk (`walk.cube_walk`), the hit's point (`look.point_lanes_of`), its diffuse direct light
    (`look.direct_lanes`, shadowed by `visible(l, start, direction, distance)` for the lights in
    `shadowed`) times its albedo, plus its `emission`, times the path's throughput. A path that
    misses ends; a dead path walks no cell (its reach −1). -> radiance (three lanes: what the hits
    gave), steps (the walks' lookups, int lanes), and with `escapes` per bounce (escaped there: a
    0/1 lane, the throughput and the direction, three lanes each), whose sky the caller adds."""
    zero = x[0] * 0.0
    radiance, throughput, alive = [zero] * 3, [zero + 1.0] * 3, zero == 0.0
    walk, steps, left = cube_walk(q.r, q.g), lanes.to_int32(zero), []

    def lit(l, start, direction, distance):  # a dead path's shadow ray walks nowhere either
        return visible(l, start, direction, lanes.where(alive, zero + distance, zero - 1.0))

    for bounce in range(bounces):
        d = bounce_direction_lanes(normal, *bounce_uniform_lanes(cells, bounce, zero))
        o = [x[c] + eps * normal[c] for c in range(3)]
        met, t, axis, material, (_, cell), _, walked = walk(o, d, lanes.where(alive, zero + math.inf, zero - 1.0))
        steps = steps + walked
        hit = alive & met  # (a lane: on torch a walk that no path entered gives a number)
        if escapes:
            left.append((lanes.where(alive & ~hit, 1.0, 0.0), throughput, d))
        alive = hit
        # a miss's hit is no cell: its point is taken at the start, of the first material, and masked
        point = point_lanes_of(q, o, d, lanes.where(alive, t, 0.0), cell, axis, lanes.where(alive, material, 1))
        incoming, _, _ = direct_lanes(q, point, [zero] * 3, lit, shadowed)
        own = [point.albedo[c] * incoming[c] + (point.emission[c] if emission else 0.0) for c in range(3)]
        radiance = [radiance[c] + lanes.where(alive, throughput[c] * own[c], 0.0) for c in range(3)]
        throughput = [throughput[c] * point.albedo[c] for c in range(3)]
        x, normal = point.x, point.face_normal
    return SimpleNamespace(radiance=radiance, steps=steps, escapes=left)


class PathGI:
    """The batch's GI paths (`voxels`: its `Stacked` voxels; `plan` its `VoxelPass`) traced by
    `tracer`, their hits shaded by `shading`'s look and lit by `direct`'s lights; `sky(directions
    [n, 3], s [n]) -> [n, 3]` what paths that leave the grid see (None: black)."""

    def __init__(self, voxels: Stacked, plan, tracer: VoxelTracer, shading: Shading, direct: DirectLight,
                 sky: Callable[[Tensor, Tensor], Tensor] | None):
        self.p, self.plan, self.tracer, self.shading, self.direct, self.sky = voxels, plan, tracer, shading, direct, sky

    def __call__(self, point: ShadingPoint, s: Tensor, keys: Tensor, distance: Tensor) -> Tensor:
        """The mean incoming radiance [n, 3] of `voxels.gi`'s paths from the hits `point`
        (scenes s [n], hash keys [n, 3], camera distance [n]): cosine-weighted, so the estimate is
        the plain path mean."""
        gi, n = self.p.gi, s.shape[0]
        S = gi.samples
        if gi.lod is None:
            cells, owner = path_keys(keys, S), None
            ps = s.repeat_interleave(S)
            x, normal = point.x.repeat_interleave(S, dim=0), point.face_normal.repeat_interleave(S, dim=0)
        else:
            counts = lod_counts(distance, S, take(gi.lod.near, s), take(gi.lod.far, s), gi.lod.samples)
            cells, owner = lod_keys(keys, counts, S)
            ps, x, normal = s[owner], point.x[owner], point.face_normal[owner]
        # start a thousandth of a voxel off the face so the DDA starts in the empty cell in front of it
        eps = take(1e-3 * self.tracer.grid.voxel_size, ps)
        radiance, steps, escapes = self._trace(x, normal, int32_bits(cells), ps, eps)
        self.tracer.count(steps)
        for escaped, throughput, d in escapes:  # the sky of the paths that left the grid, bounce by bounce
            ids = (escaped > 0).nonzero().squeeze(1)
            if ids.numel():
                radiance.index_add_(0, ids, throughput[ids] * self.sky(d[ids], ps[ids]))
        if owner is None:
            return radiance.view(n, S, 3).mean(dim=1)
        return torch.zeros_like(point.x).index_add_(0, owner, radiance) / counts[:, None].to(radiance.dtype)

    def _trace(self, x: Tensor, normal: Tensor, cells: Tensor, s: Tensor, eps: Tensor) -> tuple[Tensor, Tensor, list]:
        """`path_lanes` of paths from `x` off `normal` [m, 3] (hash cells [m, 3] int32, scenes s [m],
        offsets `eps` [m]): one Dr.Jit kernel where the walks are kernels, no air lies on a light's
        way and every shadow ray leaving the voxels has the lanes of what it crosses, else on torch
        columns. -> (radiance [m, 3], steps [m], per bounce (escaped [m], throughput [m, 3],
        direction [m, 3]) where the scene has a sky)."""
        plan, shading = self.plan, self.shading
        shadowed = {use.light: use for use in plan.shadows}
        kw = dict(bounces=self.p.gi.bounces, shadowed=shadowed, emission=plan.emission, escapes=self.sky is not None)
        inside = None
        if shading.beside and self.tracer.drjit and x.shape[0] and shading.occluder_lanes is not None:
            inside = shading.occluder_lanes(shading.beside, s)
        kernel = (self.tracer.drjit and all(light.through is None for light in self.direct.lights)
                  and (not shading.beside or inside is not None))
        widths = (3, 1) + (1, 3, 3) * (self.p.gi.bounces if kw["escapes"] else 0)
        if kernel and x.shape[0]:
            out = traced_columns(lambda lane: self._kernel_lanes(x, normal, cells, s, eps, inside, lane, kw), x, widths,
                                 lambda: [e for k in (inside or {}).values() for e in k.evals()])
            for k in (inside or {}).values():
                k.count()
        else:
            out = self._torch_lanes(x, normal, cells, s, eps, kw)
        escapes = [out[i:i + 3] for i in range(2, len(out), 3)]
        return out[0], out[1].round().long(), escapes

    def _kernel_lanes(self, x, normal, cells, s, eps, inside, lane, kw) -> list:
        """`path_lanes` traced in the kernel: its outputs as `traced_columns` takes them."""
        q = look_inputs(self.p, self.plan, self.direct.tables, self.tracer.grid, self.direct.lights, s,
                        lanes.per_scene_lanes(s), lanes.ints_of, lanes.floats_of, kernel=True)
        out = path_lanes(q, lanes.vector_lanes(x), lanes.vector_lanes(normal), [lanes.ints_of(c) for c in cells.unbind(1)],
                         lane(eps), visible=visible_beside(q, inside) if kw["shadowed"] else None, **kw)
        return [*out.radiance, lanes.to_float(out.steps, out.radiance[0]), *(v for e in out.escapes
                                                                           for v in (e[0], *e[1], *e[2]))]

    def _torch_lanes(self, x, normal, cells, s, eps, kw) -> list:
        """`path_lanes` on torch columns (the reference), its shadow rays the direct light's
        (`DirectLight.shadow_rays`): the kernel's outputs as tensors."""
        q = look_inputs(self.p, self.plan, self.direct.tables, self.tracer.grid, self.direct.lights, s,
                        lambda v: lanes.columns(take(v, s)), lambda c: c.to(torch.int32), lambda c: c.to(x.dtype),
                        kernel=False)
        stack = lambda v: torch.stack(v, dim=1)  # noqa: E731
        out = path_lanes(q, lanes.columns(x), lanes.columns(normal), list(cells.unbind(1)), eps,
                         visible=self.direct.shadow_rays(s, lambda name: nullcontext()), **kw)
        return [stack(out.radiance), out.steps.to(x.dtype),
                *(v for e in out.escapes for v in (e[0], stack(e[1]), stack(e[2])))]
