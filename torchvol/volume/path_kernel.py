"""The path tracer's paths (`path.trace_lanes`) as one Dr.Jit kernel a call (several samples of a
chunk's rays, `path.PATH_LANES`): every path a loop
per lane over its scatterings, its delta and ratio tracking loops inside it, each volume's density
in lanes (`density_lanes.crossing`), the draws the same hash as eager's. The plan runs it where
every volume's density and bounds are written in lanes, in float32 on the CPU."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ..ops import lanes
from ..runtime.threads import set_drjit_threads
from .density_lanes import crossing
from .emission import EMISSION_MAPS
from .path import path_inputs, trace_lanes, with_air


def trace_kernel(m, lights: list, rays, key: Tensor, bounces: int, channel: Tensor | None = None,
                 behind: Tensor | None = None) -> list[Tensor]:
    """`trace_lanes` of camera `rays` [n] (paths of keys `key` [n], int32; colours `channel` [n]
    where the scene has air, `path.hero_channels`; the sky `behind` each ray [n, 3], None: black)
    through the media `m`
    (`path.Media`) lit by `lights`, as one Dr.Jit kernel; each volume's evaluations counted.
    -> the results as tensors ([n, 3] for the three-lane ones), as `path.trace_eager` gives them."""
    import drjit as dr

    set_drjit_threads()
    s = rays.scene_index
    per_ray = lanes.per_scene_lanes(s)
    solids = [crossing(state, s, per_ray) for state in m.vols]

    def volume(v, state):
        glow = None
        if state.plan.emission_map is not None:
            inputs, fn = EMISSION_MAPS[state.plan.emission_map].caps["lanes"]
            table = inputs(state.params.emission_map.value, lanes_to(per_ray))
            glow = lambda x, density: fn(table, x, density)  # noqa: E731
        return solids[v].interval, glow

    def sigma(v, x, mask):
        return dr.if_stmt((), mask, lambda: solids[v].sigma_t * solids[v].density(x, None),
                          lambda: dr.zeros(type(x[0]), dr.width(x[0])))

    lane = lambda x: lanes.lanes_of(x, lanes.floats_of)  # noqa: E731
    q = path_inputs(m, lights, lanes.lanes_inputs(s, per_ray), volume)
    q.sigma, q.behind = sigma, [0.0] * 3 if behind is None else lane(behind)
    if m.surface is not None:
        q.surface = m.surface(s, per_ray, rays.origins[:, 0], kernel=True)
    q = with_air(q, m, None if channel is None else lanes.ints_of(channel), per_ray)
    res = trace_lanes(q, lane(rays.origins), lane(rays.directions), lanes.ints_of(key), bounces=bounces,
                      marched_first=m.marched_first)
    dr.eval(res)
    dr.sync_thread()
    for state, evals in zip(m.vols, res[13:]):
        n = int(np.array(evals).astype(np.int64).sum())
        state.field.counts.density_evals += n
        state.field.evals += n
    out = [lanes.tensor_of(x).to(rays.origins.device) for x in res[:13]]
    return [torch.stack(out[0:3], 1), torch.stack(out[3:6], 1), torch.stack(out[6:9], 1), out[9], out[10], out[11], out[12]]


def lanes_to(per_ray):
    """The `to` a lanes input builder takes: per scene -> lanes."""
    from types import SimpleNamespace

    return SimpleNamespace(per_lane=per_ray)


__all__ = ["trace_kernel"]
