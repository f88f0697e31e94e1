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
as under `dda.traverse`: the block records each step's cells, and the callback runs after it. The
voxel fog, the one callback on the primary walk of most voxel scenes, is summed inside the kernel
instead (`fused_traverse(..., fog=)`, `fog.FogWalk`): the same sums in the same order.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from ..ops.mathops import take_rows
from ..runtime.compilation import exact_kernel
from .dda import Hits, Visit, start
from .fog import FogWalk

__all__ = ["BLOCK", "fused_traverse", "walk_block"]

# steps a block runs before finished slots are dropped: a block costs about 30 µs of call overhead
# and a compaction about 10 eager gathers, while a finished slot still rides along in the block
BLOCK = 8
MIN_SLOTS = 4


def walk_block(state: list[Tensor], rays: list[Tensor], table: Tensor, strides: Tensor, max_steps: Tensor,
               fog_table: Tensor | None = None, distance: Tensor | None = None, *, steps: int, limited: bool,
               record: bool, switch: int = 2):
    """`steps` DDA steps of N slots.

    state: cx, cy, cz [N] int32, the cell to look up next; t [N], its entry distance; axis [N]
    int32, its entry axis; n [N] int32, lookups so far; alive [N] bool; t_exit [N], material [N]
    int32 (0: no hit), the result of finished slots; with fog, fog_tau [N], the fog's optical
    depth so far. rays: o, d [N, 3] (grid coordinates); lo, hi [N, 3] int32, the cell range; base
    [N] long, the flat index of cell (0, 0, 0) in the ray's scene (`flat = base + (k·Y + j)·X +
    i`); t_max [N] (read where `limited`); with fog, its rows [N] long (`fog.FogWalk`).
    table [M] uint8: the flattened material grids; strides [2] long: (Y, X); max_steps [] int32;
    fog_table [B·Y] or None (`fog.FogWalk.table`); distance [M] uint8 or None: the grids'
    Chebyshev distance fields, flattened as `table` (`dda.hybrid_traverse`: a slot in a cell k ≥
    `switch` cells from any occupied one first jumps across the empty cube around it; a jump
    counts as a step).
    -> (the state after the block, records): with `record` each step's visits (each [steps, N]:
    visited, cx, cy, cz, t_in, t_out, hit), with fog each step's fog visits (empty, cx, cy, cz,
    tau, fog_tau after it), else None."""
    cx, cy, cz, t, axis, n, alive, t_exit, material, *fog_tau = state
    o, d, lo, hi, base, t_max, *fog_rows = rays
    ox, oy, oz = o.unbind(1)
    dx, dy, dz = d.unbind(1)
    lx, ly, lz = lo.unbind(1)
    hx, hy, hz = hi.unbind(1)
    records = []
    for _ in range(steps):
        flat = base + (cz.long() * strides[0] + cy.long()) * strides[1] + cx.long()
        if distance is not None:
            k = take_rows(distance, torch.where(alive, flat, torch.zeros_like(flat))).to(torch.int32)
            jump = alive & (k >= switch)
            t_new, cx, cy, cz = _jump(jump, k - 1, t, (cx, cy, cz), o, d, lo, hi)
            t, n = torch.where(jump, t_new, t), n + jump.to(torch.int32)
            flat = base + (cz.long() * strides[0] + cy.long()) * strides[1] + cx.long()
        mat = take_rows(table, torch.where(alive, flat, torch.zeros_like(flat))).to(torch.int32)
        n = n + alive.to(torch.int32)
        hit = alive & (mat > 0)
        ax, t_next, nx, ny, nz = _next_cell((cx, cy, cz), (ox, oy, oz), (dx, dy, dz))
        t_out = torch.where(hit, t, t_next)
        if record:
            records.append((alive, cx, cy, cz, t, t_out, hit))
        if fog_table is not None:
            empty, tau, fog_tau[0] = _fog_step(alive, hit, cy, t, t_out, fog_rows[0], fog_table, fog_tau[0])
            records.append((empty, cx, cy, cz, tau, fog_tau[0]))
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
    state = [cx, cy, cz, t, axis, n, alive, t_exit, material, *fog_tau]
    return state, (tuple(torch.stack(column) for column in zip(*records)) if records else None)


def _next_cell(cells: tuple, o: tuple, d: tuple):
    """`dda.dda_step`'s crossings and tie rule, per column: cells, o, d three [N] columns (int32,
    float, float). -> (the axis crossed [N] int32, the distance to it [N], the next cell's three
    [N] int32 columns)."""
    (cx, cy, cz), (ox, oy, oz), (dx, dy, dz) = cells, o, d
    sx, sy, sz = (_crossing(c, oc, dc) for c, oc, dc in ((cx, ox, dx), (cy, oy, dy), (cz, oz, dz)))
    x_first, y_before_z = (sx <= sy) & (sx <= sz), sy <= sz
    ax = torch.where(x_first, 0, torch.where(y_before_z, 1, 2)).to(torch.int32)
    t_next = torch.minimum(torch.minimum(sx, sy), sz)
    nx = cx + torch.where(ax == 0, torch.sign(dx), 0).to(torch.int32)
    ny = cy + torch.where(ax == 1, torch.sign(dy), 0).to(torch.int32)
    nz = cz + torch.where(ax == 2, torch.sign(dz), 0).to(torch.int32)
    return ax, t_next, nx, ny, nz


def _fog_step(alive: Tensor, hit: Tensor, cy: Tensor, t: Tensor, t_out: Tensor, row0: Tensor, fog_table: Tensor,
              fog_tau: Tensor):
    """The fog's eager callback (passes/fog.py), per slot: the same products, the same order of
    sums. The fog over [t, t_out] [N] in the empty cells (alive [N] bool and not hit) at height
    `cy` [N] int32; `row0` [N] long, the ray's first row of `fog_table`. -> (empty [N] bool, τ
    [N], fog_tau [N] after it)."""
    empty = alive & ~hit
    row = torch.where(alive, row0 + cy.long(), torch.zeros_like(row0))
    tau = take_rows(fog_table, row) * (t_out - t).clamp_min(0.0)
    return empty, tau, torch.where(empty, fog_tau + tau, fog_tau)


def _jump(jump: Tensor, r: Tensor, t: Tensor, cells: tuple, o: Tensor, d: Tensor, lo: Tensor, hi: Tensor):
    """`dda.hybrid_traverse`'s jump, per column: across the empty cube [cell − r, cell + r] to the
    last cube cell on the ray, where `jump` [N] (elsewhere the cells stay). r, t [N]; cells three
    [N] int32; o, d [N, 3]; lo, hi [N, 3] int32. -> (the exit distance [N], the three columns)."""
    exits = []
    for a, c in enumerate(cells):
        da = d[:, a]
        zero = da == 0
        far = torch.where(da > 0, c + r + 1, c - r).to(d.dtype)
        exits.append(torch.where(zero, torch.full_like(far, torch.inf), (far - o[:, a]) / torch.where(zero, torch.ones_like(far), da)))
    t_new = torch.maximum(torch.minimum(torch.minimum(exits[0], exits[1]), exits[2]), t)
    moved = []
    for a, c in enumerate(cells):
        da = d[:, a]
        p = o[:, a] + t_new * da
        before = torch.where(da > 0, torch.ceil(p) - 1, torch.floor(p)).to(torch.int32)
        before = torch.minimum(torch.maximum(before, torch.maximum(c - r, lo[:, a])), torch.minimum(c + r, hi[:, a] - 1))
        moved.append(torch.where(jump, before, c))
    return t_new, *moved


def _crossing(cell: Tensor, o: Tensor, d: Tensor) -> Tensor:
    """`dda._crossings` for one axis: the distance [N] to the next plane (inf where d = 0)."""
    zero = d == 0
    plane = (cell + (d > 0).to(torch.int32)).to(d.dtype)
    side = (plane - o) / torch.where(zero, torch.ones_like(d), d)
    return torch.where(zero, torch.full_like(side, torch.inf), side)


_COMPILED: dict = {}


def compiled_block() -> Callable:
    """`walk_block` under torch.compile (dynamic shapes), built once per process: one graph per
    (limited, records or jumps) and dtype, up to 16, each for every size; eager where it cannot
    be compiled (`compilation.exact_kernel`)."""
    if "block" not in _COMPILED:
        _COMPILED["block"] = exact_kernel(walk_block, "the voxel walk")
    return _COMPILED["block"]


def fused_traverse(origins: Tensor, directions: Tensor, table: Tensor, base: Tensor, strides: Tensor, lo, hi, *,
                   max_steps: int, t_min: Tensor | None = None, t_max: Tensor | None = None,
                   visit: Visit | None = None, fog: FogWalk | None = None, distance: Tensor | None = None,
                   switch: int = 2, compiled: bool = True, block: int = BLOCK) -> Hits:
    """`dda.traverse` with the lookup a gather from `table` [M] uint8 (the flattened material grids:
    cell (i, j, k) of ray r is ``table[base[r] + (k·Y + j)·X + i]``, strides = (Y, X) long, every
    cell of [lo, hi) inside the table) and the steps run `block` at a time by `walk_block`
    (compiled under `compiled`). origins, directions [R, 3]; base [R] long; lo, hi [3] or [R, 3]
    long. The same `Hits` as `dda.traverse`, bitwise, and the same `visit` calls. `fog` (not with
    `visit`): the voxel fog accumulated inside the kernel, filled in as `FogWalk` says.
    `distance` [M] uint8 (the grids' Chebyshev distance fields, flattened as `table`; not with
    `visit` or `fog`): `dda.hybrid_traverse`'s walk instead, jumping from cells `switch` or more
    cells from any occupied one, with its hits and steps."""
    if (visit is not None) + (fog is not None) + (distance is not None) > 1:
        raise ValueError("fused_traverse: visit, fog and distance are exclusive (each its own records or steps)")
    dev = origins.device
    out, ok, t0, cell0, axis0, lo, hi = start(origins, directions, lo, hi, t_min, t_max)
    run = compiled_block() if compiled else walk_block
    flags = {"steps": block, "limited": t_max is not None, "record": visit is not None, "switch": switch}
    idx = ok.nonzero().squeeze(1)
    i32 = torch.int32
    t_first = take_rows(t0, idx)
    state = [*(x.contiguous() for x in take_rows(cell0, idx).to(i32).unbind(1)), t_first,
             take_rows(axis0, idx).to(i32), torch.zeros_like(idx, dtype=i32), torch.ones_like(idx, dtype=torch.bool),
             torch.zeros_like(t_first), torch.zeros_like(idx, dtype=i32)]
    # t_max is unread when unlimited: any [N] tensor holds its place
    rays = [take_rows(x, idx) for x in (origins, directions, lo.to(i32), hi.to(i32), base, t0 if t_max is None else t_max)]
    if fog is not None:
        fog.tau = origins.new_zeros(origins.shape[0])
        state.append(torch.zeros_like(t_first))
        rays.append(take_rows(fog.rows, idx))
    shared = (table, strides, torch.tensor(max_steps, dtype=i32, device=dev), None if fog is None else fog.table,
              distance)
    while idx.numel():
        result, records = _call(run, state, rays, shared, flags)
        if visit is not None:
            _replay(visit, idx, records)
        if fog is not None:
            fog.visits.append(_fog_visits(idx, records))
        alive = result[6]
        finished = (~alive).nonzero().squeeze(1)
        if finished.numel():
            _write_finished(out, fog, take_rows(idx, finished), finished, result)
        keep = alive.nonzero().squeeze(1)
        if keep.numel() == idx.numel():
            state = result
            continue
        idx = take_rows(idx, keep)
        state = [take_rows(v, keep) for v in result]
        rays = [take_rows(v, keep) for v in rays]
    return out


def _write_finished(out: Hits, fog: FogWalk | None, g: Tensor, finished: Tensor, result: list[Tensor]) -> None:
    """Writes the slots `finished` [F] of a block's `result` state (`walk_block`'s) to their rays
    `g` [F] in `out` (and the fog's τ in `fog`)."""
    cx, cy, cz, t, axis, n, alive, t_exit, material, *fog_tau = result
    cells = torch.stack([take_rows(v, finished) for v in (cx, cy, cz)], 1).long()
    out.cell.index_copy_(0, g, cells)
    out.steps.index_copy_(0, g, take_rows(n, finished).long())
    out.t_exit.index_copy_(0, g, take_rows(t_exit, finished))
    if fog is not None:
        fog.tau.index_copy_(0, g, take_rows(fog_tau[0], finished))
    m = take_rows(material, finished)
    hit = (m > 0).nonzero().squeeze(1)
    if hit.numel():
        gh, fh = take_rows(g, hit), take_rows(finished, hit)
        out.hit.index_fill_(0, gh, True)
        out.material.index_copy_(0, gh, take_rows(m, hit).long())
        out.axis.index_copy_(0, gh, take_rows(axis, fh).long())
        out.t.index_copy_(0, gh, take_rows(t, fh))


def _step_rows(idx: Tensor, visited: Tensor) -> tuple[Tensor, Tensor, list[int]]:
    """The visits of a block in `dda.traverse`'s order (step by step, slots in order): their flat
    rows in the [steps, N] records, their ray ids, and how many each step has."""
    rows = visited.reshape(-1).nonzero().squeeze(1)
    return rows, take_rows(idx, rows % visited.shape[1]), visited.sum(dim=1).tolist()


def _replay(visit: Visit, idx: Tensor, records: tuple) -> None:
    """Call `visit` once per step of a block with that step's visited slots (`walk_block`'s
    records), as `dda.traverse` calls it: one gather of the whole block's visits, then a view per
    step (a gather per step and record was a third of a recorded walk)."""
    visited, *columns = records
    rows, ids, counts = _step_rows(idx, visited)
    cx, cy, cz, t_in, t_out, hit = (take_rows(v.reshape(-1), rows) for v in columns)
    cells = torch.stack([cx, cy, cz], 1).long()
    first = 0
    for count in counts:
        if count:
            part = slice(first, first + count)
            visit(ids[part], cells[part], t_in[part], t_out[part], hit[part])
            first += count


def _fog_visits(idx: Tensor, records: tuple) -> tuple[Tensor, Tensor, Tensor]:
    """A block's fog visits (`FogWalk.visits`' entries) from `walk_block`'s fog records; the
    weights' exp runs eagerly, as the callback's does."""
    empty, *columns = records
    rows, ids, _ = _step_rows(idx, empty)
    cx, cy, cz, tau, so_far = (take_rows(v.reshape(-1), rows) for v in columns)
    return ids, torch.stack([cx, cy, cz], 1).long(), tau * torch.exp(-so_far)


def _call(run: Callable, state: list, rays: list, shared: tuple, flags: dict):
    """`run(state, rays, *shared, **flags)`; fewer than `MIN_SLOTS` slots run repeated up to that
    many, since a compiled kernel specialises on sizes 0 and 1, and dynamo ties a first size equal
    to another input's (2: strides; 3: a ray's coordinates) to it: either compiles again later."""
    n = state[0].shape[0]
    if n >= MIN_SLOTS:
        return run(state, rays, *shared, **flags)
    pad = torch.arange(MIN_SLOTS, device=state[0].device) % n
    state, records = run(*([x.index_select(0, pad) for x in group] for group in (state, rays)), *shared, **flags)
    return [x[:n].clone() for x in state], None if records is None else tuple(v[:, :n].clone() for v in records)
