"""The path tracer's tracking (`path.track_lanes`) as one Dr.Jit kernel per call: every path's
delta or ratio tracking a loop per lane, each volume's density in lanes (`density_lanes.crossing`),
the draws the same hash as eager's. Where a volume's density has no lanes form, eager tracks."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ..ops import lanes
from ..runtime.threads import set_drjit_threads
from .density_lanes import crossing, lanes_of, per_scene_lanes, writes_in_lanes
from .path import MAX_TENTATIVE, track_lanes


def supported(vols: list) -> bool:
    """Whether every volume's density and bounds are written in lanes (the kernel can track)."""
    return all(writes_in_lanes(v) for v in vols)


def track_kernel(m, o: Tensor, d: Tensor, s: Tensor, t0: Tensor, t1: Tensor, total: Tensor, key: Tensor, count: Tensor,
                 *, collide: bool) -> list[Tensor]:
    """`track_lanes` of rays o, d [n, 3] of scenes s [n] (spans t0, t1 [V, n], majorant sums
    `total` [n]) for paths of keys `key` and counters `count` [n] (int32) in `m` (`path.Media`), as
    one Dr.Jit kernel; each volume's evaluations counted. -> its results as tensors."""
    import drjit as dr

    set_drjit_threads()
    per_ray = per_scene_lanes(s)
    solids = [crossing(v, s, per_ray) for v in m.vols]

    def sigma(v, x, mask):
        return dr.if_stmt((), mask, lambda: solids[v].sigma_t * solids[v].density(x, None),
                          lambda: dr.zeros(type(x[0]), dr.width(x[0])))

    lane = lambda x: lanes_of(x, lanes.floats_of)  # noqa: E731
    out = track_lanes(lane(o), lane(d), [lane(x) for x in t0], [lane(x) for x in t1], lane(total), sigma,
                      lanes.ints_of(key), lanes.ints_of(count), collide=collide, steps=MAX_TENTATIVE)
    dr.eval(out)
    dr.sync_thread()
    for v, e in zip(m.vols, out[7:]):
        n = int(np.array(e).astype(np.int64).sum())
        v.field.counts.density_evals += n
        v.field.evals += n
    return [torch.from_numpy(np.array(x)).to(o.device) for x in out[:7]]


__all__ = ["supported", "track_kernel"]
