"""The plain DDA walk as one Dr.Jit kernel: `walk_step`, one DDA step of every ray in lanes
(`ops.lanes`), looped per ray by `drjit_traverse` (`drjit.while_loop`), the grid lookup inside (a
gather from the flattened material grids).

`dda.traverse` runs a step as ~40 small eager ops on the active rays and compacts them after every
step; on a 2-core machine those ops, not the arithmetic, are the walk (a 128² voxel-terrain
primary walk: 84 steps, 310 k ray-steps, 36 ms eager). A step's crossings, tie rule and
distance-field jump are written once, in lanes (`dda.next_cell_lanes`, `dda.jump_lanes`): the
eager walk runs them on torch columns, the kernel on Dr.Jit arrays, so the kernel gives
`dda.traverse`'s and `dda.hybrid_traverse`'s hits bitwise (tests/voxel/test_walk.py), and the
voxel fog's and glow's sums too (their per-cell terms gathered from tables the eager callback reads
as well: `fog.FogWalk`, `fog.GlowWalk`).
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import torch
from torch import Tensor

from ..noise import lattice as noise
from ..noise.lattice import hash3_lanes
from ..ops import lanes
from ..ops.mathops import take_rows
from ..runtime.threads import set_drjit_threads
from ..schema.batch import Stacked
from .dda import Hits, jump_lanes, next_cell_lanes, start, start_lanes
from .fog import FogWalk, GlowWalk
from .grid import VoxelGrid
from .shade import rounded_lanes

__all__ = ["cell_ranges", "cube_walk", "drjit_traverse", "in_cells", "int_table", "occupied_lanes", "rounded_walk", "visible_walk", "walk_inputs",
           "walk_step"]


def walk_step(state, r: SimpleNamespace, g: SimpleNamespace):
    """One DDA step of every slot, in lanes (`ops.lanes`; Dr.Jit arrays in `drjit_traverse`'s loop).

    state (a list): cx, cy, cz (int32), the cell to look up next; t, its entry distance; axis
    (int32), its entry axis; n (int32), lookups so far; alive (bool); t_exit, material (int32, 0:
    no hit), the result of finished slots; then the sums: with fog, fog_tau, the fog's optical depth
    so far; with glow, the glow summed over the cells visited so far (the hit cell included). The
    rays `r`: o, d (grid coordinates), lo, hi (int32, the cell range): three lanes each; base, the
    flat index of cell (0, 0, 0) in the ray's scene (`flat = base + (k·Y + j)·X + i`); t_max or
    None; fog_row or None (`fog.FogWalk.rows`). The tables `g`: table (the flattened material
    grids), distance or None (their Chebyshev distance fields: `dda.hybrid_traverse`'s jump from
    a cell k ≥ `switch` cells from any occupied one across the empty cube around it, a jump
    counted as a step), fog or None (`fog.FogWalk.table`), glow or None (`fog.GlowWalk.table`),
    y, x (the strides), max_steps, switch.
    -> (the state after it, (this step's visit record (visited, cx, cy, cz, t_in, t_out, hit),
    its fog record (empty, cx, cy, cz, tau, fog_tau after it) or None))."""
    cx, cy, cz, t, axis, n, alive, t_exit, material, *sums = state
    zero = lanes.int_like(0, cx)
    if g.distance is not None:
        flat = r.base + (cz * g.y + cy) * g.x + cx
        k = lanes.to_int32(lanes.gather(g.distance, lanes.where(alive, flat, zero)))
        jump = alive & (k >= g.switch)
        t_new, jx, jy, jz = jump_lanes(k - 1, t, (cx, cy, cz), r)
        cx, cy, cz = lanes.where(jump, jx, cx), lanes.where(jump, jy, cy), lanes.where(jump, jz, cz)
        t, n = lanes.where(jump, t_new, t), n + lanes.to_int32(jump)
    flat = r.base + (cz * g.y + cy) * g.x + cx
    mat = lanes.to_int32(lanes.gather(g.table, lanes.where(alive, flat, zero)))
    n = n + lanes.to_int32(alive)
    hit = alive & (mat > 0)
    ax, t_next, nx, ny, nz = next_cell_lanes((cx, cy, cz), r.o, r.d)
    t_out = lanes.where(hit, t, t_next)
    visit = (alive, cx, cy, cz, t, t_out, hit)
    fog = None
    if g.fog is not None:
        empty = alive & ~hit
        tau = lanes.gather(g.fog, lanes.where(alive, r.fog_row + cy, zero)) * lanes.clamp_min(t_out - t, 0.0)
        sums[0] = lanes.where(empty, sums[0] + tau, sums[0])
        fog = (empty, cx, cy, cz, tau, sums[0])
    if g.glow is not None:
        sums[-1] = lanes.where(alive, sums[-1] + lanes.gather(g.glow, lanes.where(alive, flat, zero)), sums[-1])
    inside = ((nx >= r.lo[0]) & (nx < r.hi[0]) & (ny >= r.lo[1]) & (ny < r.hi[1]) & (nz >= r.lo[2])
              & (nz < r.hi[2]))
    if r.t_max is not None:
        inside = inside & (t_next <= r.t_max)
    keep = alive & ~hit & inside & (n < g.max_steps)
    done = alive & ~hit & ~keep
    material = lanes.where(hit, mat, material)
    t_exit = lanes.where(hit, t, lanes.where(done, lanes.where(inside, t, t_next), t_exit))
    cx, cy, cz = lanes.where(keep, nx, cx), lanes.where(keep, ny, cy), lanes.where(keep, nz, cz)
    t, axis = lanes.where(keep, t_next, t), lanes.where(keep, ax, axis)
    return [cx, cy, cz, t, axis, n, keep, t_exit, material, *sums], (visit, fog)


def drjit_traverse(origins: Tensor, directions: Tensor, table: Tensor, base: Tensor, strides: Tensor, lo, hi, *,
                   max_steps: int, t_min: Tensor | None = None, t_max: Tensor | None = None,
                   distance: Tensor | None = None, switch: int = 2, fog: FogWalk | None = None,
                   glow: GlowWalk | None = None, scene: Tensor | None = None) -> Hits:
    """`dda.traverse` as one Dr.Jit kernel: each ray's start (`dda.start_lanes`) and whole walk a
    loop (`drjit.while_loop`) of `walk_step`, the same functions the eager walks run; the lookup a
    gather from `table` [M] uint8 (the flattened material grids: cell (i, j, k) of ray r is
    ``table[base[r] + (k·Y + j)·X + i]``, strides = (Y, X) long, every cell of [lo, hi) inside the
    table). origins, directions [R, 3] float32; base [R] long; lo, hi [3] or [R, 3] long; or, with
    `scene` [R] long, base (B,) and lo, hi (B, 3) of each ray's scene, gathered inside the kernel
    (a ray's own copies cost ~12 torch passes over the rays a walk).
    `distance` [M] uint8 (the grids' Chebyshev distance fields, flattened as `table`):
    `dda.hybrid_traverse`'s walk instead, jumping from cells `switch` or more cells from any
    occupied one, with its hits and steps. `table`, `distance` may be `int_table`s already. The
    same `Hits` as `dda.traverse`, bitwise (tests/voxel/test_walk.py). With `fog`, its τ and its
    light (`FogWalk.light`, no visits): the walk runs twice, first marking every empty cell it
    visits, whose light `fog.irradiance` then gives, then summing τ · e^(−τ so far) · that light ·
    colour per ray, in the eager callback's order (its exp Dr.Jit's: within float rounding of eager's).
    With `glow`, each ray's sum of its table over the cells it visits (`GlowWalk.total`, eager's bits)."""
    import drjit as dr
    from drjit.llvm import Float, Int32

    R = origins.shape[0]
    if fog is not None:
        fog.tau, fog.light = origins.new_zeros(R), origins.new_zeros(R, 3)
    if glow is not None:
        glow.total = origins.new_zeros(R)
    if R == 0:
        lo, hi = (lo, hi) if scene is None else (take_rows(lo, scene), take_rows(hi, scene))
        return start(origins, directions, lo, hi, t_min, t_max)[0]
    set_drjit_threads()
    floats = lanes.floats_of
    lo_l, hi_l, base_l = cell_ranges(lo, hi, base, scene, R, origins.device)
    r = SimpleNamespace(o=lanes.vector_lanes(origins), d=lanes.vector_lanes(directions),
                        lo=lo_l, hi=hi_l, base=base_l, t_max=None if t_max is None else floats(t_max), fog_row=None)
    g = SimpleNamespace(table=int_table(table), distance=None if distance is None else int_table(distance), fog=None,
                        glow=None if glow is None else floats(glow.table), y=int(strides[0]), x=int(strides[1]),
                        max_steps=dr.opaque(Int32, max_steps), switch=switch)
    ok, t0, cell0, axis0 = start_lanes(r.o, r.d, r.lo, r.hi, None if t_min is None else floats(t_min), r.t_max)
    sums = tuple(dr.zeros(Float, R) for walk in (fog, glow) if walk is not None)
    state = (*cell0, t0, axis0, dr.zeros(Int32, R), ok, dr.zeros(Float, R), dr.zeros(Int32, R), *sums)
    if fog is None:
        result = dr.while_loop(state, lambda *x: x[6], lambda *x: tuple(walk_step(list(x), r, g)[0]), mode="symbolic")
    else:
        result = _fog_walks(fog, state, r, g, floats, origins)
    out = _hit_lanes(result, ok, t0, axis0)
    dr.eval(out)
    dr.sync_thread()
    return _hits(out, fog, glow, origins.device)


def cell_ranges(lo, hi, base: Tensor, scene: Tensor | None, R: int, device) -> tuple[list, list, object]:
    """Cell ranges and flat bases as int32 lanes of R rays (`drjit_traverse`'s, `shade_kernel`'s):
    per ray (`scene` None: lo, hi [3] or [R, 3], base [R]) or gathered inside the kernel by each
    ray's `scene` [R] from its scene's (lo, hi (B, 3), base (B,))."""
    ints = lanes.ints_of
    if scene is None:
        lo, hi = (torch.as_tensor(x, device=device).to(torch.int32).expand(R, 3) for x in (lo, hi))
        return [ints(c) for c in lo.unbind(1)], [ints(c) for c in hi.unbind(1)], ints(base)
    import drjit as dr
    from drjit.llvm import Int32

    rows = ints(scene)
    of = lambda t: dr.gather(Int32, ints(t), rows)  # noqa: E731
    return [of(c) for c in lo.unbind(1)], [of(c) for c in hi.unbind(1)], of(base)


def _hit_lanes(result: tuple, ok, t0, axis0) -> tuple:
    """The walk's hits in lanes, from its final state and start (ok, t0, axis0): `dda.start`'s for
    rays that never enter, the walk's where they hit; chosen and widened to int64 in the walk's
    own kernel (in torch each was another pass over the rays). -> (hit, cell (three int64 lanes
    raveled: [R, 3] as rows), axis, t, material, steps, t_exit, *sums)."""
    import drjit as dr
    from drjit.llvm import Array3i64, Float, Int64

    cx, cy, cz, t, axis, n, _, t_exit, material, *sums = result
    hit = material > 0
    cell = dr.ravel(Array3i64(Int64(cx), Int64(cy), Int64(cz)))  # written as rows [R, 3]: no stack in torch
    return (hit, cell, Int64(dr.select(hit, axis, axis0)),
            dr.select(hit, t, dr.select(ok, t0, Float(math.inf))), Int64(material), Int64(n), t_exit, *sums)


def _hits(out: tuple, fog: FogWalk | None, glow: GlowWalk | None, device) -> Hits:
    """The `Hits` [R] of `_hit_lanes` (evaluated), and the fog's τ in `fog`, the glow's sum in `glow`."""
    hit, cell, axis, t, material, n, t_exit, *sums = (lanes.tensor_of(v).to(device) for v in out)
    if fog is not None:
        fog.tau = sums[0]
    if glow is not None:
        glow.total = sums[-1]
    return Hits(hit=hit, cell=cell.view(-1, 3), axis=axis, t=t, material=material, steps=n, t_exit=t_exit)


def _fog_walks(fog: FogWalk, state: tuple, r: SimpleNamespace, g: SimpleNamespace, floats, like: Tensor):
    """`drjit_traverse`'s two walks with the fog (`state` with its τ): the first marks the empty
    cells visited, the second sums their light; fills `fog.light` [R, 3]. -> the walk's final state."""
    import drjit as dr
    from drjit.llvm import Float, Int32

    r.fog_row, g.fog = lanes.ints_of(fog.rows), lanes.floats_of(fog.table)
    cells = dr.width(g.table)
    seen = dr.zeros(Int32, cells)

    def flat(record):
        _, cx, cy, cz, *_ = record
        return r.base + (cz * g.y + cy) * g.x + cx

    def marking(*x):
        new, (_, record) = walk_step(list(x), r, g)
        dr.scatter(seen, Int32(1), flat(record), active=record[0])
        return tuple(new)

    dr.eval(dr.while_loop(state, lambda *x: x[6], marking, mode="symbolic"), seen)
    unique = lanes.tensor_of(seen).nonzero().squeeze(1)
    light = torch.zeros(3, cells, dtype=torch.float32)  # channel-major: each channel's row a table as it is
    light.index_copy_(1, unique, fog.irradiance(unique.to(like.device)).to(torch.float32).cpu().T)
    light = [Float(row.numpy()) for row in light]
    color = [floats(c) for c in fog.color.unbind(1)]

    def summing(*x):
        new, (_, record) = walk_step(list(x[:-3]), r, g)
        empty, tau, so_far = record[0], record[4], record[5]
        weight = tau * dr.exp(-so_far)
        at = flat(record)
        sums = [dr.select(empty, x[-3 + c] + (weight * dr.gather(Float, light[c], at, empty)) * color[c], x[-3 + c])
                for c in range(3)]
        return (*new, *sums)

    result = dr.while_loop(state + tuple(dr.zeros(Float, dr.width(state[0])) for _ in range(3)), lambda *x: x[6],
                           summing, mode="symbolic")
    light = lanes.interleaved(result[-3:])
    dr.eval(result[:-3], light)  # (the light as rows only)
    fog.light = lanes.rows_of(light, 3).to(like)
    return result[:-3]


def occupied_lanes(r: SimpleNamespace, g: SimpleNamespace):
    """occupied(x, y, z) -> 1.0 where int lanes (x, y, z) are an occupied cell of each lane's grid,
    else 0.0 (outside its range too), in lanes: `r`'s lo, hi and base (`walk_inputs`' rays, or
    `cell_ranges`'), `g`'s table and strides y, x. AO's lookups (`shade.ao_lanes`)."""

    def occupied(x, y, z):
        inside = (x >= r.lo[0]) & (x < r.hi[0]) & (y >= r.lo[1]) & (y < r.hi[1]) & (z >= r.lo[2]) & (z < r.hi[2])
        at = lanes.where(inside, r.base + (z * g.y + y) * g.x + x, lanes.int_like(0, x))
        return lanes.where(inside & (lanes.gather(g.table, at) > 0), 1.0, 0.0)

    return occupied


def int_table(table):
    """A flattened uint8 grid [M] as a Dr.Jit Int32 array (Dr.Jit gathers 32-bit lanes); one
    already converted as it is (a tracer converts its grids once)."""

    return lanes.ints_of(table) if isinstance(table, Tensor) else table



# -----------------------------------------------------------------------------------------------
# Walks in lanes, for kernels that walk inside their own loops (the path tracer's, the rounded voxels')


def walk_inputs(grid: VoxelGrid, s: Tensor, per_lane, ints, *, kernel: bool, max_steps: int):
    """`walk_step`'s rays (each lane's cell range, flat base and placement; the rays' own o, d and
    t_max are the walk's) and tables (the grids, their distance fields where the traversal is
    hybrid, the strides and the step limit `max_steps`), as lanes of rays of scenes `s` [n]
    (`per_lane`: per scene -> lanes; `ints`: an integer tensor -> lanes; `kernel`: Dr.Jit's, else
    torch columns)."""
    if kernel:  # gathered by scene in the kernel
        bases, strides = grid.scene_base()
        lo, hi, base = cell_ranges(grid.lo, grid.hi, bases, s, s.shape[0], s.device)
    else:
        bases, strides = grid.flat_base(s)
        lo, hi = ([ints(c) for c in take_rows(x, s).to(torch.int32).unbind(1)] for x in (grid.lo, grid.hi))
        base = ints(bases)
    r = SimpleNamespace(lo=lo, hi=hi, base=base, origin=per_lane(grid.origin), size=per_lane(grid.voxel_size), fog_row=None)
    if kernel:
        import drjit as dr
        from drjit.llvm import Int32

        steps = dr.opaque(Int32, max_steps)
        table = int_table(grid.flat_materials)
        distance = None if grid.flat_distance is None else int_table(grid.flat_distance)
    else:
        steps, table = max_steps, grid.flat_materials.to(torch.int32)
        distance = None if grid.flat_distance is None else grid.flat_distance.to(torch.int32)
    g = SimpleNamespace(table=table, distance=distance, fog=None, glow=None, y=int(strides[0]), x=int(strides[1]),
                        max_steps=steps, switch=2)
    return r, g


def in_cells(r: SimpleNamespace, o: list, d: list) -> dict:
    """World rays o, d (three lanes each) in the grid's cell units (`r`: `walk_inputs`' rays)."""
    return {"o": [(o[c] - r.origin[c]) / r.size for c in range(3)], "d": [d[c] / r.size for c in range(3)]}


def cube_walk(r: SimpleNamespace, g: SimpleNamespace):
    """The DDA walk (`walk_step`) of the rays and tables `r`, `g` (`walk_inputs`) -> walk(o, d,
    t_max, t_min=None) of world rays o, d (three lanes each) from t_min (None: 0) up to t_max ->
    (hit, t, entry axis, material, (the rays in grid units, the cell (three int lanes)), None: the
    face's normal, the lookups it took)."""

    def walk(o: list, d: list, t_max, t_min=None):
        ray = SimpleNamespace(**vars(r), **in_cells(r, o, d), t_max=t_max)
        ok, t0, cell, axis = start_lanes(ray.o, ray.d, ray.lo, ray.hi, t_min, t_max)
        zero = lanes.int_like(0, cell[0])
        state = [*cell, t0, axis, zero, ok, t0 * 0.0, zero]
        cx, cy, cz, t, axis, n, alive, t_exit, material = lanes.while_loop(
            state, lambda *x: x[6], lambda *x: walk_step(list(x), ray, g)[0])
        return material > 0, t, axis, material, (ray, [cx, cy, cz]), None, n

    return walk


def visible_walk(r: SimpleNamespace, g: SimpleNamespace, max_steps):
    """The shadow ray's walk: visible(o, d, t_max) -> 1.0 where the plain cube walk (`cube_walk`, no
    distance-field skip) of world rays o, d (three lanes each) meets no occupied cell within
    `max_steps` cells (an int lane) before t_max (a lane; inf: a sun), else 0.0 (`r`, `g`:
    `walk_inputs`)."""
    walk = cube_walk(r, SimpleNamespace(**{**vars(g), "distance": None, "max_steps": max_steps}))
    return lambda o, d, t_max: lanes.where(walk(o, d, t_max)[0], 0.0, 1.0)


def rounded_walk(cubes, r: SimpleNamespace, rounded: Stacked, per_lane, *, kernel: bool):
    """`voxels.rounded`'s walk, the marched voxels' (`passes.rounded`) and the path tracer's
    (`path_surface`): the first occupied cell the cube walk `cubes` (`cube_walk`) finds, refined by
    sphere tracing its rounded box (`shade.rounded_lanes`, radius `radius_min` + `radius_range` ·
    hash3(cell)); a ray that misses it walks on from the cell's exit, up to `retries` times (`r`:
    the walk's rays, `walk_inputs`). -> walk(o, d, t_max, first=None) -> `cubes`' results with t on
    the rounded box and its normal (three lanes) instead of None, and the lookups and tracing
    steps taken after `first` (the first cube walk's results, where the caller walked it already;
    None: walked here)."""
    low, span, threshold = per_lane(rounded.radius_min), per_lane(rounded.radius_range), per_lane(rounded.threshold)
    steps, retries = int(rounded.steps), int(rounded.retries)

    def radius(cell: list):  # `noise.hash3`'s value, from its one source in either backend
        if not kernel:
            return low + span * noise.hash3(torch.stack(cell, dim=1), rounded.seed, dtype=low.dtype)
        return low + span * lanes.to_float((hash3_lanes(*cell, rounded.seed) >> 8) & 0xFFFFFF, low) * 2.0**-24

    def walk(o: list, d: list, t_max, first=None):
        met, t_c, ax, mat, (_, cell), _, _ = cubes(o, d, t_max) if first is None else first
        ray = SimpleNamespace(**in_cells(r, o, d))

        def body(found, t, axis, material, cx, cy, cz, nx, ny, nz, met, t_c, ax, mat, ccx, ccy, ccz, tries, going, extra):
            cell = [ccx, ccy, ccz]
            centre = [lanes.to_float(c, t_c) + 0.5 for c in cell]
            local = [ray.o[i] + t_c * ray.d[i] - centre[i] for i in range(3)]
            ok, advance, normal = rounded_lanes(local, d, radius(cell), steps=steps, threshold=threshold)
            on_box = t_c + advance * r.size
            trying = going & met
            now, missed = trying & ok & (on_box <= t_max), trying & ~ok  # (a box past t_max: none before it)
            keep = lambda a, b: lanes.where(now, a, b)  # noqa: E731
            found, t, axis, material = found | now, keep(on_box, t), keep(ax, axis), keep(mat, material)
            cx, cy, cz = keep(ccx, cx), keep(ccy, cy), keep(ccz, cz)
            nx, ny, nz = keep(normal[0], nx), keep(normal[1], ny), keep(normal[2], nz)
            again = missed & (tries < retries)
            exit_t = next_cell_lanes(tuple(cell), tuple(ray.o), tuple(ray.d))[1]  # walk on from the cell's exit
            met, t_c, ax, mat, (_, cell), _, n = cubes(o, d, lanes.where(again, t_max, 0.0), lanes.where(again, exit_t, 0.0))
            extra = extra + lanes.to_int32(trying) * steps + lanes.where(again, n, 0)
            return (found, t, axis, material, cx, cy, cz, nx, ny, nz, met, t_c, ax, mat, *cell, tries + 1, again, extra)

        zero = o[0] * 0.0
        none = lanes.to_int32(zero)
        state = [zero > 1.0, zero + math.inf, none, none, none, none, none, zero, zero, zero, met, t_c, ax, mat, *cell,
                 none, met, none]
        out = lanes.while_loop(state, lambda *x: x[18], body)
        found, t, axis, material, cx, cy, cz, nx, ny, nz = out[:10]
        return found, t, axis, material, (ray, [cx, cy, cz]), [nx, ny, nz], out[19]

    return walk
