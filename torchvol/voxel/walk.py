"""The plain DDA walk in blocks of steps, each block one compiled kernel.

`dda.traverse` runs a step as ~40 small eager ops on the active rays and compacts them after every
step; on a 2-core machine those ops, not the arithmetic, are the walk (a 128² voxel-terrain
primary walk: 84 steps, 310 k ray-steps, 36 ms eager). Here `walk_block` runs `BLOCK` steps of
every slot at once, the grid lookup inside (a gather from the flattened material grids), finished
slots frozen by `where`: torch.compile turns it into one fused C++ loop over the slots. Between
blocks finished slots are written out and dropped.

`walk_block` is pure arithmetic on plain tensors and, eager, the twin of the compiled kernel; both
give `dda.traverse`'s hits bitwise (the same crossing formula, compares and one division an axis;
tests/voxel/test_walk.py). A `visit` callback sees the same cells, in the same order and calls,
as under `dda.traverse`: the block records each step's cells, and the callback runs after it.
"""

from __future__ import annotations

from typing import Callable, Optional

import torch
from torch import Tensor

from ..mathops import take_rows
from .dda import Hits, Visit, _bounds, _entry_axis, _enter, start_cells

__all__ = ["BLOCK", "walk_block", "fused_traverse"]

# steps a block runs before finished slots are dropped: a block costs about 30 µs of call overhead
# and a compaction about 10 eager gathers, while a finished slot still rides along in the block
BLOCK = 8


def walk_block(cx: Tensor, cy: Tensor, cz: Tensor, t: Tensor, axis: Tensor, n: Tensor, alive: Tensor,
               t_exit: Tensor, material: Tensor, o: Tensor, d: Tensor, lo: Tensor, hi: Tensor, base: Tensor,
               t_max: Tensor, table: Tensor, strides: Tensor, max_steps: Tensor, *, steps: int, limited: bool,
               record: bool):
    """`steps` DDA steps of N slots.

    cx, cy, cz [N] int32: the cell to look up next; t [N]: its entry distance; axis [N] int32: its
    entry axis; n [N] int32: lookups so far; alive [N] bool; t_exit [N], material [N] int32 (0: no
    hit): the result of finished slots. o, d [N, 3]: the rays (grid coordinates); lo, hi [N, 3]
    int32: the cell range; base [N] long: the flat index of cell (0, 0, 0) in the ray's scene
    (`flat = base + (k·Y + j)·X + i`); t_max [N] (read where `limited`); table [M] uint8: the
    flattened material grids; strides [2] long: (Y, X); max_steps [] int32.
    -> the state after the block (cx, cy, cz, t, axis, n, alive, t_exit, material), and with
    `record` the visits (each [steps, N]: visited, cx, cy, cz, t_in, t_out, hit)."""
    ox, oy, oz = o.unbind(1)
    dx, dy, dz = d.unbind(1)
    lx, ly, lz = lo.unbind(1)
    hx, hy, hz = hi.unbind(1)
    visits = []
    for _ in range(steps):
        flat = base + (cz.long() * strides[0] + cy.long()) * strides[1] + cx.long()
        mat = take_rows(table, torch.where(alive, flat, torch.zeros_like(flat))).to(torch.int32)
        n = n + alive.to(torch.int32)
        hit = alive & (mat > 0)
        # dda.dda_step's crossings and tie rule, per column
        sx, sy, sz = (_crossing(c, oc, dc) for c, oc, dc in ((cx, ox, dx), (cy, oy, dy), (cz, oz, dz)))
        x_first, y_before_z = (sx <= sy) & (sx <= sz), sy <= sz
        ax = torch.where(x_first, 0, torch.where(y_before_z, 1, 2)).to(torch.int32)
        t_next = torch.minimum(torch.minimum(sx, sy), sz)
        nx = cx + torch.where(ax == 0, torch.sign(dx), 0).to(torch.int32)
        ny = cy + torch.where(ax == 1, torch.sign(dy), 0).to(torch.int32)
        nz = cz + torch.where(ax == 2, torch.sign(dz), 0).to(torch.int32)
        if record:
            visits.append((alive, cx, cy, cz, t, torch.where(hit, t, t_next), hit))
        inside = (nx >= lx) & (nx < hx) & (ny >= ly) & (ny < hy) & (nz >= lz) & (nz < hz)
        if limited:
            inside = inside & (t_next <= t_max)
        keep = alive & ~hit & inside & (n < max_steps)
        done = alive & ~hit & ~keep
        material = torch.where(hit, mat, material)
        t_exit = torch.where(hit, t, torch.where(done, torch.where(inside, t, t_next), t_exit))
        cx, cy, cz = torch.where(keep, nx, cx), torch.where(keep, ny, cy), torch.where(keep, nz, cz)
        t, axis = torch.where(keep, t_next, t), torch.where(keep, ax, axis)
        alive = keep
    state = (cx, cy, cz, t, axis, n, alive, t_exit, material)
    if not record:
        return state
    return state, tuple(torch.stack(column) for column in zip(*visits))


def _crossing(cell: Tensor, o: Tensor, d: Tensor) -> Tensor:
    """`dda._crossings` for one axis: the distance [N] to the next plane (inf where d = 0)."""
    zero = d == 0
    plane = (cell + (d > 0).to(torch.int32)).to(d.dtype)
    side = (plane - o) / torch.where(zero, torch.ones_like(d), d)
    return torch.where(zero, torch.full_like(side, torch.inf), side)


_COMPILED: dict = {}


def compiled_block() -> Callable:
    """`walk_block` under torch.compile (dynamic shapes), built once per process: one graph per
    (steps, limited, record), each for every size."""
    if "block" not in _COMPILED:
        _COMPILED["block"] = torch.compile(walk_block, dynamic=True)
    return _COMPILED["block"]


def fused_traverse(origins: Tensor, directions: Tensor, table: Tensor, base: Tensor, strides: Tensor, lo, hi, *,
                   max_steps: int, t_min: Optional[Tensor] = None, t_max: Optional[Tensor] = None,
                   visit: Optional[Visit] = None, compiled: bool = True, block: int = BLOCK) -> Hits:
    """`dda.traverse` with the lookup a gather from `table` [M] uint8 (the flattened material grids:
    cell (i, j, k) of ray r is ``table[base[r] + (k·Y + j)·X + i]``, strides = (Y, X) long, every
    cell of [lo, hi) inside the table) and the steps run `block` at a time by `walk_block`
    (compiled under `compiled`). origins, directions [R, 3]; base [R] long; lo, hi [3] or [R, 3]
    long. The same `Hits` as `dda.traverse`, bitwise, and the same `visit` calls."""
    R, dev = origins.shape[0], origins.device
    lo, hi = _bounds(lo, origins), _bounds(hi, origins)
    ok, t0 = _enter(origins, directions, lo, hi, t_min, t_max)
    cell0 = start_cells(origins, directions, t0, lo, hi)
    axis0 = _entry_axis(origins, directions, lo, hi)
    out = Hits(
        hit=torch.zeros(R, dtype=torch.bool, device=dev), cell=cell0.clone(), axis=axis0.clone(),
        t=torch.where(ok, t0, torch.full_like(t0, torch.inf)), material=torch.zeros(R, dtype=torch.long, device=dev),
        steps=torch.zeros(R, dtype=torch.long, device=dev), t_exit=torch.where(ok, t0, torch.zeros_like(t0)),
    )
    run = compiled_block() if compiled else walk_block
    flags = dict(steps=block, limited=t_max is not None, record=visit is not None)
    idx = ok.nonzero().squeeze(1)
    i32 = torch.int32
    c = take_rows(cell0, idx).to(i32)
    state = [*(x.contiguous() for x in c.unbind(1)), take_rows(t0, idx), take_rows(axis0, idx).to(i32), torch.zeros_like(idx, dtype=i32),
             torch.ones_like(idx, dtype=torch.bool), torch.zeros_like(take_rows(t0, idx)), torch.zeros_like(idx, dtype=i32)]
    rays = [take_rows(x, idx) for x in (origins, directions, lo.to(i32), hi.to(i32), base)]
    limit = take_rows(t_max, idx) if t_max is not None else rays[0][:, 0]  # unread when unlimited
    cap = torch.tensor(max_steps, dtype=i32, device=dev)
    while idx.numel():
        result = _call(run, state, [*rays, limit], (table, strides, cap), flags)
        if visit is not None:
            result, visits = result
            for alive, vx, vy, vz, t_in, t_out, hit in zip(*visits):
                rows = alive.nonzero().squeeze(1)
                if rows.numel():
                    cells = torch.stack([take_rows(v, rows) for v in (vx, vy, vz)], 1).long()
                    visit(take_rows(idx, rows), cells, *(take_rows(v, rows) for v in (t_in, t_out, hit)))
        cx, cy, cz, t, axis, n, alive, t_exit, material = result
        finished = (~alive).nonzero().squeeze(1)
        if finished.numel():
            g = take_rows(idx, finished)
            cells = torch.stack([take_rows(v, finished) for v in (cx, cy, cz)], 1).long()
            out.cell.index_copy_(0, g, cells)
            out.steps.index_copy_(0, g, take_rows(n, finished).long())
            out.t_exit.index_copy_(0, g, take_rows(t_exit, finished))
            m = take_rows(material, finished)
            hit = (m > 0).nonzero().squeeze(1)
            if hit.numel():
                gh, fh = take_rows(g, hit), take_rows(finished, hit)
                out.hit.index_fill_(0, gh, True)
                out.material.index_copy_(0, gh, take_rows(m, hit).long())
                out.axis.index_copy_(0, gh, take_rows(axis, fh).long())
                out.t.index_copy_(0, gh, take_rows(t, fh))
        keep = alive.nonzero().squeeze(1)
        if keep.numel() == idx.numel():
            state = list(result)
            continue
        idx = take_rows(idx, keep)
        state = [take_rows(v, keep) for v in result]
        rays = [take_rows(v, keep) for v in rays]
        limit = take_rows(limit, keep)
    return out


def _call(run: Callable, state: list, rays: list, shared: tuple, flags: dict):
    """`run(*state, *rays, *shared, **flags)`; one slot runs as two copies of itself, since a
    compiled kernel specialises on a size of 1 (it would compile again for a walk's last ray)."""
    if state[0].shape[0] != 1:
        return run(*state, *rays, *shared, **flags)
    twice = [x.repeat(2, *[1] * (x.dim() - 1)) for x in (*state, *rays)]
    result = run(*twice[:len(state)], *twice[len(state):], *shared, **flags)
    if flags["record"]:
        state, visits = result
        return tuple(x[:1] for x in state), tuple(v[:, :1] for v in visits)
    return tuple(x[:1] for x in result)
