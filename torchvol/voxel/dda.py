"""Batched, branchless grid traversal (Amanatides–Woo DDA) over a flat batch of rays.

Everything here works in *grid coordinates*: cell ``(i, j, k)`` is the unit cube ``[i, i+1) ×
[j, j+1) × [k, k+1)``. A caller places a grid in the world by ``g = (p − origin) / voxel_size``
and passes ``directions / voxel_size``: the ray parameter ``t`` is then the world distance along a
unit world direction.

Conventions (shared by `traverse`, `hybrid_traverse` and the slow `reference_traverse`):

* Rays enter the cell range ``[lo, hi)`` through ray/box intersection: ``t0 = max(t_near, t_min)``.
  The first cell is the one the ray occupies just *after* ``t0``: per axis ``floor(p)`` when the
  direction is ≥ 0, ``ceil(p) − 1`` when it is negative (so an origin on a plane moving down starts
  below it), clamped into the range.
* The next crossing on axis ``a`` is at ``(plane_a − o_a) / d_a`` with ``plane = cell + (d > 0)``,
  recomputed from the origin at every step (no accumulated ``sideDist`` drift); axes with
  ``d_a = 0`` never cross.
* **Ties** (two or three crossings at exactly the same t): exactly one axis steps, the first of x,
  y, z (``argmin`` returns the first minimum); the other axes step on the following iterations.
  The seeds' ``step()`` form would move two axes at once and skip the edge cell.
* A ray stops at the first cell whose material id is > 0 (a hit), when it leaves the range, when
  its next crossing lies beyond ``t_max``, or after ``max_steps`` occupancy lookups.
* The hit face: ``axis`` is the axis of the last step (for a hit in the first cell, the axis of the
  entry face: the last of the axes whose slab entry is latest, again the x, y, z tie order), ``t``
  is the crossing distance of that face (``t0`` for the first cell).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Callable, Optional

import torch
from torch import Tensor

from ..geometry.rays import box_interval
from ..ops import lanes
from ..ops.mathops import take_rows

__all__ = ["Hits", "Lookup", "hybrid_traverse", "reference_traverse", "start", "start_lanes", "traverse"]

# lookup(cells [N, 3] long, ray_ids [N] long) -> material ids [N] (long, 0 = empty)
Lookup = Callable[[Tensor, Tensor], Tensor]
# visit(ray_ids [N], cells [N, 3], t_in [N], t_out [N], hit [N] bool): called for every visited cell
Visit = Callable[[Tensor, Tensor, Tensor, Tensor, Tensor], None]


@dataclass
class Hits:
    """Per ray [R]: `hit` bool; `cell` [R, 3] long (the hit cell; the last visited one for misses);
    `axis` long (0, 1, 2: the axis of the face the ray entered `cell` through); `t` (entry distance
    of that face; inf for rays that never entered the range); `material` long (0 for misses);
    `steps` long (occupancy lookups; for hybrid traversal also the distance-field steps);
    `t_exit` (where traversal ended: the hit, the range exit or the step limit)."""

    hit: Tensor
    cell: Tensor
    axis: Tensor
    t: Tensor
    material: Tensor
    steps: Tensor
    t_exit: Tensor


def _bounds(x, like: Tensor) -> Tensor:
    return torch.as_tensor(x, device=like.device).to(torch.long).expand(like.shape[0], 3)


def start_lanes(o, d, lo, hi, t_min, t_max):
    """Where rays o, d (three float lanes each) enter the cell range [lo, hi) (three int lanes each),
    in lanes (`ops.lanes`: torch columns in `start`, Dr.Jit arrays in `walk.drjit_traverse`): (whether
    they enter, their entry t0 (0 where not), first cell (three int32 lanes), entry axis (int32)).
    `t_min`, `t_max`: lanes or None. See the module notes."""
    lo_f, hi_f = [lanes.to_float(x, o[0]) for x in lo], [lanes.to_float(x, o[0]) for x in hi]
    t_near, t_far = box_interval(o, d, lo_f, hi_f)
    t0 = lanes.clamp_min(t_near, 0.0) if t_min is None else lanes.maximum(t_near, t_min)
    ok = (t_near <= t_far) & (t0 <= t_far)
    if t_max is not None:
        ok = ok & (t0 <= t_max)
    t0 = lanes.where(ok, t0, 0.0)
    cell = []
    for i in range(3):  # the cell just after t0: floor(p), or ceil(p) − 1 moving down; clamped into the range
        p = o[i] + t0 * d[i]
        c = lanes.where(d[i] < 0, lanes.ceil(p) - 1.0, lanes.floor(p))
        c = lanes.where(lanes.isfinite(c), c, 0.0)
        # clamped before the conversion: the same cell as converting first, and no int32 overflow
        cell.append(lanes.to_int32(lanes.minimum(lanes.maximum(c, lo_f[i]), hi_f[i] - 1.0)))
    t_lo = []
    for i in range(3):  # each slab's entry; an axis the ray runs along never entered
        zero = d[i] == 0
        ds = lanes.where(zero, 1.0, d[i])
        t_lo.append(lanes.where(zero, float("-inf"), lanes.minimum((lo_f[i] - o[i]) / ds, (hi_f[i] - o[i]) / ds)))
    # the last axis whose slab is entered latest (the x, y, z tie order)
    axis = lanes.where((t_lo[2] >= t_lo[1]) & (t_lo[2] >= t_lo[0]), 2, lanes.where(t_lo[1] >= t_lo[0], 1, 0))
    return ok, t0, cell, lanes.to_int32(axis)


def start(o: Tensor, d: Tensor, lo, hi, t_min: Tensor | None, t_max: Tensor | None):
    """Where R rays o, d [R, 3] enter the cell range [lo, hi) ([3] or [R, 3]): (the `Hits` of rays
    that find nothing, the rays that enter [R] bool, their entry t0 [R], first cell [R, 3] long and
    entry axis [R], lo and hi as [R, 3] long). The start of every eager walk (`traverse`, `walk`):
    `start_lanes` on torch columns."""
    R, dev = o.shape[0], o.device
    lo, hi = _bounds(lo, o), _bounds(hi, o)
    ok, t0, cell, axis = start_lanes(o.unbind(1), d.unbind(1), lo.unbind(1), hi.unbind(1), t_min, t_max)
    cell0, axis0 = torch.stack(cell, 1).long(), axis.long()
    out = Hits(
        hit=torch.zeros(R, dtype=torch.bool, device=dev), cell=cell0.clone(), axis=axis0.clone(),
        t=torch.where(ok, t0, torch.full_like(t0, torch.inf)), material=torch.zeros(R, dtype=torch.long, device=dev),
        steps=torch.zeros(R, dtype=torch.long, device=dev), t_exit=t0.clone(),
    )
    return out, ok, t0, cell0, axis0, lo, hi


def _sign(d):
    """sign(d) as int32 lanes: 1, −1, or 0 where d = 0."""
    return lanes.to_int32(d > 0) - lanes.to_int32(d < 0)


def next_cell_lanes(cells: tuple, o: tuple, d: tuple):
    """One DDA step's crossings and tie rule (the module notes), per column, in lanes (`ops.lanes`:
    torch columns in `traverse`, Dr.Jit arrays in `walk.walk_step`): cells, o, d three lanes each
    (int32 or long, float, float). -> (the axis crossed (int32), the distance to it, the next cell's three
    int32 lanes)."""
    (cx, cy, cz), (ox, oy, oz), (dx, dy, dz) = cells, o, d
    sx, sy, sz = (_crossing(c, oc, dc) for c, oc, dc in ((cx, ox, dx), (cy, oy, dy), (cz, oz, dz)))
    x_first, y_before_z = (sx <= sy) & (sx <= sz), sy <= sz
    ax = lanes.to_int32(~x_first) * (1 + lanes.to_int32(~y_before_z))  # 0: x first, else 1 (y) or 2 (z)
    t_next = lanes.minimum(lanes.minimum(sx, sy), sz)
    nx = cx + lanes.to_int32(ax == 0) * _sign(dx)
    ny = cy + lanes.to_int32(ax == 1) * _sign(dy)
    nz = cz + lanes.to_int32(ax == 2) * _sign(dz)
    return ax, t_next, nx, ny, nz


def jump_lanes(r, t, cells: tuple, rays: SimpleNamespace):
    """`hybrid_traverse`'s jump, per column, in lanes (torch columns or Dr.Jit arrays): across the empty cube [cell − r, cell + r]
    to the last cube cell on the ray (the caller keeps it where no jump is due). r (int32), t;
    cells three int32 lanes; `rays`' o, d, lo, hi. -> (the exit distance, the three cells)."""
    exits = []
    for a, c in enumerate(cells):
        da = rays.d[a]
        zero = da == 0
        far = lanes.to_float(lanes.where(da > 0, c + r + 1, c - r), da)
        exits.append(lanes.where(zero, math.inf, (far - rays.o[a]) / lanes.where(zero, 1.0, da)))
    t_new = lanes.maximum(lanes.minimum(lanes.minimum(exits[0], exits[1]), exits[2]), t)
    moved = []
    for a, c in enumerate(cells):
        da = rays.d[a]
        p = rays.o[a] + t_new * da
        before = lanes.to_int32(lanes.where(da > 0, -lanes.floor(-p) - 1.0, lanes.floor(p)))
        moved.append(lanes.minimum(lanes.maximum(before, lanes.maximum(c - r, rays.lo[a])),
                                   lanes.minimum(c + r, rays.hi[a] - 1)))
    return t_new, *moved


def _crossing(cell, o, d):
    """The distance to one axis' next plane (inf where d = 0), lanes; recomputed from the origin at
    every step (no accumulated drift)."""
    zero = d == 0
    plane = lanes.to_float(cell + lanes.to_int32(d > 0), d)
    side = (plane - o) / lanes.where(zero, 1.0, d)
    return lanes.where(zero, math.inf, side)


def traverse(
    origins: Tensor,
    directions: Tensor,
    lookup: Lookup,
    lo,
    hi,
    *,
    max_steps: int,
    t_min: Optional[Tensor] = None,
    t_max: Optional[Tensor] = None,
    visit: Optional[Visit] = None,
) -> Hits:
    """Plain DDA. origins, directions [R, 3] (grid coordinates; directions need not be unit);
    lo, hi [3] or [R, 3] long: the cell range [lo, hi); t_min, t_max [R] optional limits.
    Active rays are compacted every step: finished rays cost nothing (`walk.drjit_traverse` is the
    same walk as one Dr.Jit kernel)."""
    return _walk(origins, directions, lookup, lo, hi, max_steps=max_steps, t_min=t_min, t_max=t_max, visit=visit)


def hybrid_traverse(
    origins: Tensor,
    directions: Tensor,
    lookup: Lookup,
    distance: Lookup,
    lo,
    hi,
    *,
    max_steps: int,
    switch: int = 2,
    t_min: Optional[Tensor] = None,
    t_max: Optional[Tensor] = None,
) -> Hits:
    """DDA near surfaces, distance-field jumps in open space; the same hits as `traverse`.

    distance(cells, ray_ids) -> [N] long: a lower bound k on the Chebyshev distance (in cells) from
    the cell to the nearest occupied cell (`chebyshev_distance`): every cell within k − 1 rings is
    empty, so the cube of those cells contains no surface and the ray jumps to the cube's exit
    (a sphere-tracing step with the distance field's radius) when k ≥ `switch`, then resumes DDA
    from the cell it lands in. A jump never passes any occupied cell, and the DDA after it uses
    the same per-step crossing formula, so hits (and ties) are the plain DDA's. `steps` counts DDA
    lookups plus jumps; `max_steps` bounds their sum."""
    return _walk(origins, directions, lookup, lo, hi, max_steps=max_steps, t_min=t_min, t_max=t_max, distance=distance, switch=switch)


def _walk(o, d, lookup, lo, hi, *, max_steps, t_min, t_max, visit=None, distance=None, switch=2) -> Hits:
    out, ok, t0, cell0, axis0, lo, hi = start(o, d, lo, hi, t_min, t_max)
    idx = ok.nonzero().squeeze(1)
    # the active rays' state; `take_rows` (index_select) compacts it, 3–5× faster than x[ids]
    cell, t, axis, oa, da, loa, hia = (take_rows(x, idx) for x in (cell0, t0, axis0, o, d, lo, hi))
    tmax_a = None if t_max is None else take_rows(t_max, idx)
    n = torch.zeros_like(idx)  # steps taken by each active ray
    while idx.numel():
        if distance is not None:
            k = distance(cell, idx)
            j = (k >= switch).nonzero().squeeze(1)
            if j.numel():
                # jump across the empty cube [cell - r, cell + r] (r = k - 1) to the last cube cell on
                # the ray; the DDA step below then leaves the cube with the usual tie rule
                rays = SimpleNamespace(**{name: take_rows(x, j).unbind(1) for name, x in
                                          (("o", oa), ("d", da), ("lo", loa), ("hi", hia))})
                t_new, *moved = jump_lanes(take_rows(k, j) - 1, take_rows(t, j), take_rows(cell, j).unbind(1), rays)
                cell[j], t[j] = torch.stack(moved, 1).long(), t_new
                n[j] += 1
        mat = lookup(cell, idx).to(torch.long)
        n += 1
        hit = mat > 0
        ax, t_next, *new = next_cell_lanes(cell.unbind(1), oa.unbind(1), da.unbind(1))
        ax, new = ax.long(), torch.stack(new, 1)
        if visit is not None:
            visit(idx, cell, t, torch.where(hit, t, t_next), hit)
        if bool(hit.any()):
            h = hit.nonzero().squeeze(1)
            g = take_rows(idx, h)
            out.hit[g] = True
            for field, value in (("cell", cell), ("axis", axis), ("t", t), ("material", mat), ("steps", n), ("t_exit", t)):
                getattr(out, field).index_copy_(0, g, take_rows(value, h))
        within = (new >= loa) & (new < hia)
        inside = within[:, 0] & within[:, 1] & within[:, 2]
        if tmax_a is not None:
            inside &= t_next <= tmax_a
        keep = ~hit & inside & (n < max_steps)
        done = ~hit & ~keep
        if bool(done.any()):
            dn = done.nonzero().squeeze(1)
            g = take_rows(idx, dn)
            out.steps.index_copy_(0, g, take_rows(n, dn))
            out.t_exit.index_copy_(0, g, take_rows(torch.where(inside, t, t_next), dn))
            out.cell.index_copy_(0, g, take_rows(cell, dn))
        keep = keep.nonzero().squeeze(1)
        idx, cell, t, axis, oa, da, loa, hia, n = (
            take_rows(x, keep) for x in (idx, new, t_next, ax, oa, da, loa, hia, n))
        if tmax_a is not None:
            tmax_a = take_rows(tmax_a, keep)
    return out


# -----------------------------------------------------------------------------------------------
# The slow, obvious reference


def reference_traverse(origin, direction, occupied: Callable[[tuple[int, int, int]], int], lo, hi, *, max_steps: int,
                       t_min: float = 0.0):
    """One ray in plain Python floats (float64): list every plane crossing inside the box, sort them
    by (t, axis) and walk them one at a time (coincident crossings one axis after the other in x, y,
    z order), checking each cell visited. Returns (hit, cell, axis, t, steps) like `Hits`."""
    o = [float(x) for x in origin]
    d = [float(x) for x in direction]
    lo, hi = [int(x) for x in lo], [int(x) for x in hi]
    t_near, t_far, t_lo = -float("inf"), float("inf"), []
    for a in range(3):
        if d[a] == 0.0:
            t_lo.append(-float("inf"))
            if not (lo[a] <= o[a] <= hi[a]):
                return False, None, None, float("inf"), 0
            continue
        ta, tb = (lo[a] - o[a]) / d[a], (hi[a] - o[a]) / d[a]
        t_lo.append(min(ta, tb))
        t_near, t_far = max(t_near, min(ta, tb)), min(t_far, max(ta, tb))
    t0 = max(t_near, t_min)
    if not (t_near <= t_far and t0 <= t_far):
        return False, None, None, float("inf"), 0
    axis = max(a for a in range(3) if t_lo[a] == max(t_lo))
    cell = []
    for a in range(3):
        p = o[a] + t0 * d[a]
        c = math.ceil(p) - 1 if d[a] < 0 else math.floor(p)
        cell.append(min(max(c, lo[a]), hi[a] - 1))
    events = []  # (t, axis): every plane ahead inside the range
    for a in range(3):
        if d[a] == 0.0:
            continue
        planes = range(cell[a] + 1, hi[a] + 1) if d[a] > 0 else range(cell[a], lo[a] - 1, -1)
        events += [((k - o[a]) / d[a], a) for k in planes]
    events.sort()
    t, steps = t0, 0
    for i, (te, a) in enumerate([(t0, axis)] + events):
        if i:
            cell[a] += 1 if d[a] > 0 else -1
            t, axis = te, a
            if not (lo[a] <= cell[a] < hi[a]):
                return False, tuple(cell), axis, t, steps
        if steps >= max_steps:
            return False, tuple(cell), axis, t, steps
        steps += 1
        if occupied(tuple(cell)):
            return True, tuple(cell), axis, t, steps
    return False, tuple(cell), axis, t, steps
