"""The physical march as one Dr.Jit kernel per chunk: a loop per ray (its state in registers
until its march ends) through every physical medium of the ray (one volume alone, or the media of
the joint march, `volume.joint`: the ray cut into pieces at every entry and exit, the media of a
piece summed), the lights' shadow rays (marched, or looked up in the sun's grids) and the sky
light's visibility march through it and through the other volumes, under a per-sample branch
where the density passes the threshold; the step rule, dither, early termination and the depth
statistics inside it.

One source: every per-sample formula here is the eager renderer's own function, written in lanes
(`ops.lanes`) and traced here with Dr.Jit arrays: the density (its kind's ``lanes`` capability in
`fields.DENSITIES`: constant, exponential, value-noise fbm, explosion, particles, fur, the
template's cloud layer, the production cloudscape, a grid), the edge fade (`fields.edge.faded`
over the bounds' ``lanes`` depth), the shadow rays' exits and segments (the bounds' ``lanes`` interval: box,
sphere, slab, a planet's shell; `volume.shadow.shadow_segments`), the ambient graded by the bounds'
``lanes`` altitude (`volume.ambient.ambient_radiance`), the sky blend (`volume.physical.sky_blend`), the sun's grid lookup
(`volume.sun_volume.grid_transmittance`), a point light's falloff (`light.lights.point_lanes`)
and phase (`light.phase`'s ``lanes``), the multiple-scattering octaves
(`volume.multiple.octave_weights`), the emission colour map and bloom, the step rule
(`march.StepRule.length`), the integrator's step (`integrate.WEIGHTS`) and the median
(`march.median_crossing`). The suns' phase responses, constant along a ray, are the phases'
lanes too (`physical.light_responses`' values), evaluated once a ray before the loop. What else is
constant along a ray is computed by the eager code itself before the kernel runs: the dither, the
pieces, a grid's occupied span (`volume.skip`: empty space skipped as the eager march skips it),
the sun grids, the sky behind each ray (what a sky blend fades towards). `march_look` is
the seeds' alpha loop (the shader look: the template; the surface look: the fur ball) in the same
way. The eager march (`compile="off"`) is the reference the kernels are held to
(tests/volume/test_kernel_march.py).

`supports` says which volumes it renders (the plan asks once); the others run eagerly. Numbers a
dataset draws per scene are the kernel's inputs, and the settings that are numbers are its
parameters (`drjit.opaque`), so one kernel serves a whole dataset; Dr.Jit caches it on disk.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import torch
from torch import Tensor

from ..fields.heightfield import terrain_lanes, visible_lanes
from ..geometry.bounds import BOUNDS
from ..light.atmosphere import (
    AirPath,
    air_lanes,
    air_source_lanes,
    depth_transmittance_lanes,
    rows_of,
    sun_transmittance_lanes,
)
from ..light.lights import point_lanes
from ..ops import lanes
from ..runtime.threads import set_drjit_threads
from .ambient import ambient_lanes, ambient_radiance
from .density_lanes import (
    crossing,
    has_lanes,
    writes_in_lanes,
)
from .emission import EMISSION_MAPS, bloom_lanes, bloom_source
from .integrate import WEIGHTS
from .march import MarchResult, median_crossing, occupied_start
from .multiple import octave_weights
from .physical import sky_blend
from .shader_look import ambient_light, derivative_light, look_lanes, shaded
from .shadow import occluder_transmittance, segment_end, segment_reach, sun_grids
from .sun_volume import grid_transmittance
from .surface_look import look_normal, surface_colour, surface_lanes


def supports(batch, vol, uses, settings, ambient=None) -> str | None:
    """Why the kernel cannot render volume `vol` (its `Stacked` parameters) of `batch` with its
    light passes `uses` and sky-visibility pass `ambient` (None: none), or None where it can: a
    density written in lanes (constant, exponential, fbm of any noise: value noise of either hash,
    gradient or Worley noise; explosion, particles of any noise, fur, the cloudscape, a grid, its
    empty space skipped) in bounds written in lanes (sphere, box, slab, shell), physically shaded
    or in the seeds' looks, by any integrator, lit by suns and point lights with shadows (marched,
    or the sun's grid) through it and through the other volumes (each written in lanes too) and
    past the terrain and the voxels, sky light (graded by altitude or not), a sky blend, emission, its colour map
    and bloom; `settings` the render's `MarchSettings`."""
    passes = [u for u in uses if u.shadow is not None] + ([] if ambient is None else [ambient])
    checks = [
        (has_lanes(vol), f"the {vol.density.kind} density"),
        ("lanes" in BOUNDS[vol.bounds.kind].caps, f"{vol.bounds.kind} bounds"),
        (vol.shading in ("physical", "shader", "surface"), f"the {vol.shading} shading"),
        (batch.atmosphere is None or vol.shading == "physical", "a look under the [atmosphere]"),
        (settings.tolerance is None, "the error-controlled march"),
        (all(batch.lights[u.light].kind in ("sun", "point") for u in uses), "a light other than a sun or a point"),
        (all(has_lanes(batch.volumes[j]) and "lanes" in BOUNDS[batch.volumes[j].bounds.kind].caps
             for u in passes for j in u.occluders), "shadows through a volume not written in lanes"),
    ]
    return next((why for ok, why in checks if not ok), None)


def _grid_lanes(ctx, j: int, light: int, s: Tensor, per_ray) -> SimpleNamespace:
    """Volume `j`'s sun grids towards `light` (`shadow.sun_grids`) as `grid_transmittance` takes
    them for lanes of scenes `s` [n]."""
    return sun_grids(ctx, ctx.volumes[j], light).lanes(s, per_ray, lanes.pairs_of, lanes.ints_of)


def _member_inputs(ctx, vol, direction: list, s: Tensor, per_ray, behind) -> SimpleNamespace:
    """What a member's sample takes per ray, for rays of `direction` (three lanes) and scenes `s` [n],
    computed by the eager code: σ_t, albedo, what its lights and sky light take (the suns' phase
    responses, `physical.light_responses`; the ambient, `ambient.ambient_lanes`), its emission,
    colour map and bloom, and its sky blend towards the sky `behind` the rays (three lanes)."""
    import drjit as dr

    k = SimpleNamespace(direction=direction, sigma_t=per_ray(vol.params.sigma_t), albedo=per_ray(vol.params.albedo))
    inputs, k.phase = vol.phase.caps["lanes"]
    k.phase_params = inputs(vol.params.phase.value, SimpleNamespace(per_lane=per_ray))
    ms = vol.params.multiple_scattering
    k.octave_scales = [] if not vol.plan.multiple else [(per_ray(ms.a**i), per_ray(ms.c**i)) for i in range(1, ms.octaves)]
    k.lights = []
    for use in vol.plan.lights:
        light = ctx.lights[use.light]
        if not light.directional:  # its θ changes along the ray: the phase is traced per sample
            k.lights.append(SimpleNamespace(response=None, position=per_ray(light.params.position),
                                            radiant=per_ray(light.radiant), use=use, grids=None))
            continue
        # a sun's θ is the same all along a ray: its response once a ray (`physical.light_responses`),
        # evaluated before the march's loop, which reads it at every sample
        direction = per_ray(light.direction)
        response = _response(k, lanes.dot3(k.direction, direction), per_ray(light.radiant))
        dr.eval(response)
        grids = None if use.shadow is None or use.shadow.method != "grid" else {
            j: _grid_lanes(ctx, j, use.light, s, per_ray) for j in (vol.plan.index, *use.occluders)
            if not ctx.volumes[j].plan.line_integral}
        k.lights.append(SimpleNamespace(response=response, direction=direction, use=use, grids=grids,
                                        through=light.through is not None))
    if vol.plan.emissive:
        k.emission = per_ray(vol.params.emission)
    to = SimpleNamespace(per_lane=per_ray)
    if vol.plan.emission_map is not None:
        inputs, k.emission_glow = EMISSION_MAPS[vol.plan.emission_map].caps["lanes"]
        k.emission_map = inputs(vol.params.emission_map.value, to)
    if vol.plan.bloom is not None:
        k.bloom = bloom_lanes(vol.params.bloom, ctx.lights[vol.plan.bloom].params, to)
    if vol.plan.multiple:
        b = vol.params.multiple_scattering.b
        k.exponents = [per_ray(b**i) for i in range(1, vol.params.multiple_scattering.octaves)]
    if vol.plan.ambient:
        amb = vol.params.ambient
        k.ambient = ambient_lanes(vol, per_ray)
        k.ambient_direction = per_ray(torch.nn.functional.normalize(amb.direction, dim=1))
        k.ambient_sigma = per_ray(amb.sigma_scale * vol.params.sigma_t)
    if vol.plan.sky_blend:
        k.behind, k.sky_blend = behind, per_ray(vol.params.sky_blend)
    return k


def march(ctx, vols, rays, background: Tensor | None, start: Tensor, end: Tensor, active: Tensor,
          dither: Tensor | None, *, shares: bool = False, air: AirPath | None = None,
          occupied: tuple[Tensor, Tensor] | None = None) -> MarchResult:
    """The fixed march of the physical volumes `vols` (`supports` said yes for each) along a
    chunk's `rays` [R] (the sky behind them `background` [R, 3], None: black; what a sky blend
    fades towards) as one Dr.Jit kernel: each ray's span cut into pieces [start, end] [P, R]
    (`joint.pieces`; one volume alone: one piece, its chord), medium v present in piece p where
    `active` [P, V, R]; in each piece σ_t and the sources of the media present summed, as
    `joint.summed_medium` does, and the piece marched by the render's step rule from its own
    start, its first step dithered by `dither` [R] (the fraction) or not (None). `shares`: the
    radiance has V channels more, each medium's σ_t integrated (`joint.Joint.shares`). `air`: the
    `[atmosphere]` along the rays (`AirPath`), row V of `active`, as `joint.summed_medium` adds
    it (its in-scatter where present, every source seen through the air in front of it, a piece
    of air alone in the atmosphere's own step count), the suns' light reaching each volume's
    samples through it (`light.atmosphere.sun_transmittance_lanes`). `occupied` = (t_first,
    t_last) [R] (one piece): σ_t is 0 outside that span, so each ray starts at the full march's
    last segment boundary before it and stops past it, as `march.march(occupied=...)` does
    (`march.occupied_start`). -> the whole ray's `march.march` result; its steps, truncations (one
    per piece a step limit cut) and each volume's density evaluations counted in the render's stats."""
    import drjit as dr
    from drjit.llvm import Bool, Float, Int32

    count = len(ctx.volumes)
    held = active.any(dim=1)  # [P, R]: a medium in the piece, the air too
    idx = held.any(dim=0).nonzero().squeeze(1)
    air_on = None if air is None else active[:, -1]  # [P, R]
    active = active if air is None else active[:, :-1]
    result = MarchResult.empty(start[0], 3 + (len(vols) if shares else 0))
    if idx.shape[0] == 0:
        return result
    s, row, lane, per_ray = _ray_lanes(rays, idx)
    pieces = held[:, idx]  # [P, n]
    k = SimpleNamespace(
        origin=row(rays.origins), direction=row(rays.directions), dither=None if dither is None else row(dither),
        start=[row(x) for x in start], end=[row(x) for x in end],
        present=[Bool(x.cpu().numpy()) for x in pieces],
        active=[[Bool(a.index_select(0, idx).cpu().numpy()) for a in v] for v in active.unbind(1)],
        air=None if air is None else _air_inputs(air, idx, lane, row, air_on, active))
    q0 = _next_piece(k.present, dr.full(Int32, -1, len(idx)))  # the first piece with a medium on each ray
    t0, first = _first_segment(ctx, k, idx, _pick(k.start, q0), start, end, dither, occupied, lane)
    uses = [u for v in vols for u in v.plan.lights + (v.plan.ambient_sky,) if u is not None]
    needed = {v.plan.index for v in vols} | {j for u in uses for j in u.occluders}
    solids = {j: crossing(ctx.volumes[j], s, per_ray) for j in sorted(needed)}
    par = _parameters(ctx.settings)
    terrain = None if ctx.terrain is None else terrain_lanes(ctx.terrain.p, lanes.lanes_inputs(s, per_ray), torch.float32)
    blockers = SimpleNamespace(terrain=terrain, voxels=None if not any(u.voxels for u in uses) else
                               ctx.voxels.visibility_lanes(s, per_ray))
    behind = [0.0] * 3 if background is None else row(background)
    members = [SimpleNamespace(vol=v, k=(m := _member_inputs(ctx, v, k.direction, s, per_ray, behind)),
                               medium=_medium(m, v, par, solids, blockers, count, k.air)) for v in vols]
    n = len(idx)
    zero = dr.zeros(Float, n)
    state = (t0, q0, dr.zeros(Int32, n), dr.full(Float, 1.0, n), zero, zero, zero, dr.zeros(Int32, n),
             dr.full(Bool, True, n), dr.zeros(Int32, n), first,
             *(dr.zeros(Int32, n) for _ in range(count)), *(zero for _ in range(3 + (len(vols) if shares else 0))))
    out = dr.while_loop(state, lambda *x: x[8], _body(k, members, par, ctx.settings, count, shares), mode="symbolic")
    radiance = lanes.interleaved(out[11 + count:])  # (the kernel writes them as rows, not as columns too)
    dr.eval(out[:11 + count], radiance)
    dr.sync_thread()
    return _written(ctx, result, idx, out[3:8], out[9], radiance, dict(enumerate(out[11:11 + count])))


def march_look(ctx, vol, rays, background: Tensor | None, t0: Tensor, t1: Tensor, hit: Tensor,
               dither: Tensor | None) -> MarchResult:
    """The seeds' loop through volume `vol` in the shader look (`shader_look`) or lit as a surface
    (`surface_look`): alpha compositing, samples at t from a dithered start, along a chunk's
    `rays` [R] through [t0, t1]
    [R] where `hit` [R], the sky behind them `background` [R, 3] (None: black), `dither` [R] the
    start offsets in steps or None, as one Dr.Jit kernel. -> `march.march`'s result; its steps,
    truncations and density evaluations counted in the render's stats."""
    import drjit as dr
    from drjit.llvm import Bool, Float, Int32

    st, idx = ctx.settings, hit.nonzero().squeeze(1)
    result = MarchResult.empty(t0, 3)
    if idx.shape[0] == 0:
        return result
    s, row, lane, per_ray = _ray_lanes(rays, idx)
    start, end = t0.index_select(0, idx), t1.index_select(0, idx)
    span = end - start
    if dither is not None:  # `march.march`'s shader start: dithered by a fraction of a step, or in world units
        start = start + dither.index_select(0, idx) * (st.rule.length(start, span) if st.dither != "sin" else 1.0)
    behind = [dr.zeros(Float, len(idx)) for _ in range(3)] if background is None else row(background)
    to = SimpleNamespace(per_lane=per_ray)
    k = SimpleNamespace(origin=row(rays.origins), direction=row(rays.directions), t_end=row(t1),
                        span=lane(span), behind=behind, surface=vol.params.shading == "surface")
    k.look = surface_lanes(vol, to) if k.surface else look_lanes(vol, to)
    k.lights = []
    for use in vol.plan.lights:  # the shader look's derivative light: the first light only; the surface look's: every one
        light = ctx.lights[use.light]
        k.lights.append(SimpleNamespace(direction=per_ray(light.direction), irradiance=per_ray(light.radiant))
                        if light.directional else
                        SimpleNamespace(position=per_ray(light.params.position), radiant=per_ray(light.radiant)))
    solid, par, n = crossing(vol, s, per_ray), _parameters(st), len(idx)
    zero = dr.zeros(Float, n)
    state = (lane(start), dr.full(Float, 1.0, n), zero, zero, zero, dr.zeros(Int32, n), dr.full(Bool, True, n),
             dr.full(Bool, False, n), dr.zeros(Int32, n), zero, zero, zero)
    out = dr.while_loop(state, lambda *x: x[6], _look_body(k, solid, par, st), mode="symbolic")
    radiance = lanes.interleaved(out[9:])
    dr.eval(out[:9], radiance)
    dr.sync_thread()
    return _written(ctx, result, idx, out[1:6], out[7], radiance, {vol.plan.index: out[8]})


def _first_segment(ctx, k: SimpleNamespace, idx: Tensor, t0, start: Tensor, end: Tensor,
                   dither: Tensor | None, occupied: tuple[Tensor, Tensor] | None, lane):
    """Where the rays `idx` [n] start (`t0`, a lane: their first piece's start) and whether their
    first segment is dithered (a Bool lane); with `occupied` (`march`), where the skipped march
    starts and stops them (`march.occupied_start`), the stop set as `k.stop` (None: a piece stops
    at its end)."""
    import drjit as dr
    from drjit.llvm import Bool

    first, k.stop = dr.full(Bool, True, len(idx)), None
    if occupied is not None:
        assert start.shape[0] == 1, "march(occupied=...) is one piece's"
        t0, t_stop, dithered = occupied_start(start[0, idx], end[0, idx], occupied[0][idx], occupied[1][idx],
                                              rule=ctx.settings.rule, frac=None if dither is None else dither[idx])
        t0, k.stop, first = lane(t0), lane(t_stop), first if dithered is None else Bool(dithered.cpu().numpy())
    return t0, first


def _air_inputs(air: AirPath, idx: Tensor, lane, row, on: Tensor, active: Tensor) -> SimpleNamespace:
    """The air along the kernel's rays `idx` [n] as lanes (`lane`: of a tensor [n]; `row`: of the
    rows idx of a chunk's tensor, `_ray_lanes`): its values (`air_lanes`), the rays' origins in the
    planet frame, the sun's direction and irradiance; where it is (`on` [P, R]) and alone (no
    volume of `active` [P, V, R] there), a Bool lane a piece; its optical-depth table, the chunk's
    tables (`AirPath.tables`, each kernel ray reading its own ray's nodes: `fetch`), their span and
    count."""
    from drjit.llvm import Bool

    rows = lambda x: x.index_select(0, idx)  # noqa: E731
    bools = lambda x: [Bool(rows(piece).cpu().numpy()) for piece in x]  # noqa: E731
    enter = rows(air.enter)
    span = (rows(air.leave) - enter).clamp_min(torch.finfo(enter.dtype).tiny)
    return SimpleNamespace(
        q=air_lanes(rows_of(air.air, idx), lane), origin=row(air.origins), sun_dir=row(air.sun_dir),
        sun=row(air.sun), on=bools(on), alone=bools(on & ~active.any(dim=1)), enter=lane(enter), span=lane(span),
        nodes=air.nodes, light_steps=air.light_steps, fetch=air.fetch(lanes.ints_of(idx)))


def _air_sample(a: SimpleNamespace, here, t_sample, direction):
    """The air's in-scatter where `here` (0 elsewhere) and its transmittance from the camera, three
    lanes each, at `t_sample` along `direction` (`_air_inputs` `a`): `AirPath.source` and
    `.transmittance` in lanes."""
    import drjit as dr
    from drjit.llvm import Float

    width = dr.width(t_sample)
    p = [a.origin[c] + t_sample * direction[c] for c in range(3)]
    source = dr.if_stmt((), here, lambda: tuple(air_source_lanes(p, direction, a.sun_dir, a.sun, a.q, a.light_steps)),
                        lambda: tuple(dr.zeros(Float, width) for _ in range(3)))
    return list(source), depth_transmittance_lanes(t_sample, a.enter, a.span, a.nodes, a.fetch)


def _ray_lanes(rays, idx: Tensor):
    """Dr.Jit's threads set for a kernel over the chunk's rays `idx` [n]; -> (their scenes [n],
    `row` (a chunk's tensor [R] or [R, C] -> the lanes of its rows idx, `lanes.row_lanes`), `lane`
    (a tensor [n] or [n, C] -> lanes), `per_ray` (per scene -> lanes))."""

    set_drjit_threads()
    s = rays.scene_index.index_select(0, idx)
    lane = lambda x: lanes.lanes_of(x, lanes.floats_of)  # noqa: E731
    return s, lanes.row_lanes(idx), lane, lanes.per_scene_lanes(s)


def _written(ctx, result: MarchResult, idx: Tensor, state, truncated, radiance, evals: dict) -> MarchResult:
    """A march kernel's lanes for the rays `idx` [n] written into `result` (`state`: the
    transmittance, weight sums, median and steps; `truncated`: truncations a ray, or whether;
    `radiance` its C channels as rows, `lanes.interleaved`), its steps, truncations and each volume's evaluations (`evals`, by
    index in `ctx.volumes`) counted in the render's stats. -> `result`."""
    trans, wsum, wt, median, steps = (lanes.tensor_of(v) for v in state)
    truncated = lanes.tensor_of(truncated).long()
    full = idx.shape[0] == result.steps.shape[0]  # every ray of the chunk: idx is 0..n−1, the rows as they lie

    def put(target: Tensor, value: Tensor) -> None:
        if full:
            target.copy_(value)
        else:
            target.index_copy_(0, idx, value.to(target.dtype))

    # the radiance as rows, one write: three into strided columns stalled ~2.6 ms each on 2 threads
    # under OpenMP's default (spinning) wait policy, in a process not tuned by `tune_process`
    put(result.radiance, lanes.rows_of(radiance, result.radiance.shape[1]))
    for name, value in (("transmittance", trans), ("weight_sum", wsum), ("weighted_t", wt), ("median_t", median),
                        ("steps", steps), ("truncated", truncated > 0)):
        put(getattr(result, name), value)
    ctx.counts.march_steps += int(steps.long().sum())
    ctx.counts.truncated_rays += int(truncated.sum())
    _count(ctx, evals)
    return result


def _count(ctx, evals: dict) -> None:
    """Each volume's evaluations (`evals`: by index in `ctx.volumes`, evaluated Int32 lanes) into
    the render's stats."""
    for j, e in evals.items():
        count = int(lanes.tensor_of(e).long().sum())
        ctx.counts.density_evals += count
        ctx.volumes[j].field.evals += count


def _look_body(k: SimpleNamespace, solid: SimpleNamespace, par: SimpleNamespace, st):
    """The loop body of `march_look`: one sample of `march.march`'s shader loop, its shading
    (`shader_look`'s or `surface_look`'s lanes functions) under a branch where the density passes
    the threshold."""
    import drjit as dr
    from drjit.llvm import Float, Int32

    q = k.look
    # density evaluations a lit sample adds: the derivative light's one a light, or the normal's
    lit_evals = (6 if q.gradient == "central" else 3) if k.surface else len(k.lights)

    def body(t, trans, wsum, wt, median, steps, alive, truncated, evals, red, green, blue):
        dt = st.rule.length(t, k.span)
        p = [dr.fma(t, k.direction[c], k.origin[c]) for c in range(3)]  # rounded once, as eager's addcmul
        count = None
        if par.lod is not None and solid.octaves is not None:
            count = solid.octaves - Int32(dr.floor(dr.log2(1.0 + t * par.lod)))
        density = solid.density(p, count)

        def toward(source):
            if hasattr(source, "position"):
                return point_lanes(source.position, source.radiant, p)[:2]
            return source.direction, source.irradiance

        def shade_surface():
            normal = look_normal(lambda x: solid.density(x, count), p, density, q.epsilon, gradient=q.gradient)
            colour = surface_colour(q, normal, [-c for c in k.direction], [toward(source) for source in k.lights])
            return lanes.clamp_max(density * q.alpha_scale, 1.0), colour

        def shade():
            light = ambient_light(q, p[1])
            for source in k.lights:
                direction, irradiance = toward(source)
                ahead = solid.density([p[c] + q.light_offset * direction[c] for c in range(3)], count)
                dif = derivative_light(density, ahead, scale=q.light_scale)
                light = [irradiance[c] * dif + light[c] for c in range(3)]
            alpha, colour = shaded(q, density, light, k.behind, t)
            return alpha, colour

        width = dr.width(t)
        alpha, colour = dr.if_stmt((), density > par.threshold, shade_surface if k.surface else shade,
                                   lambda: (dr.zeros(Float, width), [dr.zeros(Float, width) for _ in range(3)]))
        seg_trans = 1.0 - alpha
        radiance = [r + trans * (colour[c] * alpha) for c, r in enumerate((red, green, blue))]
        w, new_trans = trans * (1.0 - seg_trans), trans * seg_trans
        median = dr.select((trans > 0.5) & (new_trans <= 0.5), t, median)
        evals = evals + 1 + dr.select(density > par.threshold, Int32(lit_evals), Int32(0))
        steps, t_next = steps + 1, t + dt
        keep = t_next <= k.t_end
        if st.min_transmittance > 0:
            keep = keep & (new_trans >= par.min_transmittance)
        last = steps >= par.max_iterations
        return (t_next, new_trans, wsum + w, wt + w * t, median, steps, keep & ~last, keep & last, evals, *radiance)

    return body


def _parameters(st) -> SimpleNamespace:
    """The march settings `st` (`MarchSettings`) that are numbers as the kernel's parameters
    (`drjit.opaque`: one kernel for any value)."""
    import drjit as dr
    from drjit.llvm import Float, Int32

    return SimpleNamespace(
        threshold=dr.opaque(Float, st.density_threshold), lod=None if st.lod_scale is None else dr.opaque(Float, st.lod_scale),
        min_transmittance=dr.opaque(Float, st.min_transmittance), max_iterations=dr.opaque(Int32, st.rule.max_iterations))


def _medium(k: SimpleNamespace, vol, par: SimpleNamespace, solids: dict, blockers: SimpleNamespace, count: int,
            air: SimpleNamespace | None = None) -> SimpleNamespace:
    """The per-sample functions of member `vol` over its inputs `k` (`_member_inputs`), the
    parameters `par`, the volumes a ray may cross `solids` (`solid`, by index), the surfaces
    (`blockers`: the terrain's `fields.heightfield.terrain_lanes` and the voxels' walk, None each
    where the scene has none) and the air the sun shines through (`_air_inputs`, None: none):
    density(p, count), in_scatter(p, sigma_t, raw) -> (three lanes, `count` lanes of evaluations per volume)."""
    import drjit as dr
    from drjit.llvm import Float, Int32

    own = solids[vol.plan.index]

    def transmittance(p, direction, sigma_scale, use, evals, raw, distance=None, sigma_t=None, grids=None):
        """From lanes `p` (the density `raw` there) along `direction` out of the bounds or to the
        light at `distance` (None: a sun): `_own_transmittance` times what LightPass `use`'s
        occluders and surfaces let through; `evals` added to."""
        through = _own_transmittance(own, p, raw, direction, sigma_scale, use.shadow, evals, distance, sigma_t, grids)
        return through * _through_others(solids, use.occluders, _asked(blockers, use), p, direction, distance, use.shadow,
                                         grids, evals)

    def in_scatter(p, sigma_t, raw):
        """Σ over the lights of σs·p(θ)·E·T_light (octaves summed), plus σs·L_amb·V at lanes `p`
        (extinction `sigma_t`, density `raw`): three lanes (`physical.in_scatter`'s terms, in its
        order), and each volume's evaluations."""
        sigma_s = k.albedo * sigma_t
        width = dr.width(sigma_t)
        out, evals = [dr.zeros(Float, width) for _ in range(3)], [dr.zeros(Int32, width) for _ in range(count)]
        for light in k.lights:
            response, direction, distance = light.response, getattr(light, "direction", None), None
            if response is None:  # a point light: `physical.response` at this sample
                direction, distance, response = _point_response(k, light, p)
            use = light.use
            trans = None if use.shadow is None else transmittance(p, direction, k.sigma_t, use, evals, raw, distance,
                                                                  sigma_t, light.grids)
            weights = octave_weights(sigma_s, trans, k.exponents if vol.plan.multiple else [])
            radiance = [sum((response[i][c] * weights[i] for i in range(1, len(weights))), response[0][c] * weights[0])
                        for c in range(3)]
            if air is not None and getattr(light, "through", False):  # the air on the sun's way to p
                through = sun_transmittance_lanes([p[0], p[1] + air.q.planet_radius, p[2]], direction, air.q, air.light_steps)
                radiance = [radiance[c] * through[c] for c in range(3)]
            out = [out[c] + radiance[c] for c in range(3)]
        if vol.plan.ambient:
            amb = [a * sigma_s for a in ambient_radiance(k.ambient, p)]
            sky = vol.plan.ambient_sky
            if sky is not None:
                v = transmittance(p, k.ambient_direction, k.ambient_sigma, sky, evals, raw)
                amb = [a * v for a in amb]
            out = [out[c] + amb[c] for c in range(3)]
        return out, evals

    return SimpleNamespace(density=own.density, in_scatter=in_scatter, octaves=own.octaves)


def _own_transmittance(own, p, raw, direction, sigma_scale, shadow, evals, distance, sigma_t, grids):
    """Transmittance through volume `own` (`crossing`) from lanes `p` along `direction` out of its
    bounds or to the light at `distance` (None: a sun), σ_t = `sigma_scale` × density: its closed
    form where it has one (`own.depth`, from the sample's density `raw`: no evaluation), else
    `shadow.shadow_transmittance`'s march or the sun's grid (`grids`; `sigma_t` at p); its
    evaluations added to `evals`."""
    if shadow.method == "grid" and own.depth is None:
        return grid_transmittance(grids[own.index], p, sigma_t)
    exit_t = lanes.clamp(own.interval(p, direction)[1], 0.0, own.reach)
    if distance is not None:
        exit_t = lanes.minimum(exit_t, distance)
    if own.depth is not None:  # exact: no march, no grid
        through = lanes.exp(-sigma_scale * own.depth(p, direction, exit_t, raw))
    else:
        through = lanes.exp(-optical_depth(own, p, direction, exit_t, sigma_scale, shadow.steps, shadow.growth,
                                           shadow.first_step))
        evals[own.index] = evals[own.index] + shadow.steps
    return through


def _point_response(k: SimpleNamespace, light: SimpleNamespace, p):
    """A point light's direction, distance and `_response` at lanes `p` seen along the ray
    (`_member_inputs` `k`)."""
    direction, irradiance, distance = point_lanes(light.position, light.radiant, p)
    return direction, distance, _response(k, lanes.dot3(k.direction, direction), irradiance)


def _response(k: SimpleNamespace, cos, irradiance: list) -> list:
    """`physical.response` in lanes: E · p(θ) of a light of `irradiance` (three lanes) at cos θ
    `cos`, and with multiple scattering each octave's aⁱ · E · p(θ; cⁱ): per octave, three lanes."""
    response = [[e * k.phase(k.phase_params, cos, 1.0) for e in irradiance]]
    return response + [[e * (a * k.phase(k.phase_params, cos, c)) for e in irradiance] for a, c in k.octave_scales]


def optical_depth(solid, p, direction, exit_t, sigma_scale, steps, growth=1.0, first_step=None):
    """∫ σ_t along `direction` from `p` to `exit_t` (lanes) through `solid` (`solid`), σ_t =
    `sigma_scale` × its density, over `shadow.shadow_segments` (one loop in the kernel)."""
    import drjit as dr
    from drjit.llvm import Float, UInt32

    reach = Float(segment_reach(steps=steps, growth=growth, first_step=first_step))

    def segment(k, state):  # one Dr.Jit loop, not `steps` copies of the density traced
        tau, start = state
        end = segment_end(exit_t, dr.gather(Float, reach, UInt32(k)), first_step)
        mid = 0.5 * (start + end)
        return [tau + sigma_scale * solid.density([p[c] + mid * direction[c] for c in range(3)], None) * (end - start), end]

    zero = dr.zeros(Float, dr.width(exit_t))
    return lanes.fori(steps, [zero, zero], segment)[0]


def _asked(blockers: SimpleNamespace, use) -> SimpleNamespace:
    """The surfaces of `blockers` (`_medium`'s) that LightPass `use` asks its rays to see."""
    return SimpleNamespace(terrain=blockers.terrain if use.terrain else None, voxels=blockers.voxels if use.voxels else None)


def _through_others(solids: dict, occluders, blockers: SimpleNamespace, p, direction, distance, shadow, grids, evals):
    """What a shadow or sky ray from lanes `p` along `direction` up to `distance` (a lane; None:
    a sun, the sky) lets through besides its own volume (`shadow.occluder_transmittance`): each
    volume of `occluders` it crosses (`solids`, by index), its σ_t over its chord in
    `shadow.steps` equal segments or its sun grid where the ray enters it (`grids`, by volume),
    each one's evaluations added to `evals`; 0 where it meets the terrain or the voxels (`blockers`,
    `_asked`'s: the terrain's lanes and the voxels' walk, None each where not asked)."""
    import drjit as dr
    from drjit.llvm import Float, Int32

    # the terrain and the voxels first: a volume is marched only where they and the volumes before
    # it let light through (as eager does)
    reach = math.inf if distance is None else distance
    through = 1.0 if blockers.terrain is None else visible_lanes(blockers.terrain, p, direction, reach)
    if blockers.voxels is not None:
        through = through * blockers.voxels(p, direction, reach)
    for j in occluders:
        other = solids[j]
        near, far = other.interval(p, direction)
        t0 = lanes.clamp_min(near, 0.0)
        t1 = lanes.minimum(far, other.reach if distance is None else lanes.minimum(distance, other.reach))
        crosses = (t1 > t0) if isinstance(through, float) else (t1 > t0) & (through > 0.0)
        entry = [p[c] + t0 * direction[c] for c in range(3)]
        zero = lambda: dr.zeros(Float, dr.width(t0))  # noqa: E731
        if other.depth is not None:  # exact, from its density where the ray enters it
            tau = dr.if_stmt((), crosses, lambda: other.sigma_t * other.depth(entry, direction, t1 - t0), zero)
            through = through * lanes.exp(-tau)
            evals[j] = evals[j] + dr.select(crosses, Int32(1), Int32(0))
            continue
        if shadow.method == "grid":
            sigma = dr.if_stmt((), crosses, lambda: other.sigma_t * other.density(entry, None), zero)
            through = through * dr.select(crosses, grid_transmittance(grids[j], entry, sigma), 1.0)
            evals[j] = evals[j] + dr.select(crosses, Int32(1), Int32(0))
            continue
        tau = dr.if_stmt((), crosses, lambda: optical_depth(other, entry, direction, t1 - t0, other.sigma_t, shadow.steps),
                         zero)
        through = through * lanes.exp(-tau)
        evals[j] = evals[j] + dr.select(crosses, Int32(shadow.steps), Int32(0))
    return through


def occluders_supported(ctx, use) -> bool:
    """Whether `occluders` renders what LightPass `use` asks of `shadow.occluder_transmittance`:
    every occluding volume written in lanes, float32 on the CPU (the plan's `kernels`)."""
    return ctx.plan.kernels and all(writes_in_lanes(ctx.volumes[j]) for j in use.occluders)


def surface_lanes_of(ctx, uses: dict, s: Tensor) -> dict | None:
    """`occluder_lanes` of each LightPass of `uses` (by its key) for a surface's own kernel (the
    terrain's shading, the voxels'), rays of scenes `s` [n], the volumes' crossings and the
    surfaces' lanes made once for all of them; None where a kernel cannot see all they ask (a
    volume not written in lanes, eager rendering): the surface then takes `surface_shadows`."""
    if not all(occluders_supported(ctx, use) for use in uses.values()):
        return None
    shared: dict = {}
    return {key: occluder_lanes(ctx, use, s, shared) for key, use in uses.items()}


def surface_shadows(ctx, use, p: Tensor, s: Tensor, direction: Tensor, distance: Tensor,
                    times: Tensor | None = None) -> Tensor:
    """`times` [n] (None: 1; the light already reaching the points, their n·l or the voxels'
    visibility) × `shadow.occluder_transmittance` of a surface's shadow or sky ray (LightPass
    `use`), traced only where that light is > 0. Its volumes, the terrain and the voxels as one
    Dr.Jit kernel (`occluders`) where `occluders_supported`, their passes listed (their time their
    caller's). -> [n]."""
    out = p.new_ones(p.shape[0]) if times is None else times.clone()
    ids = None if times is None else (times > 0).nonzero().squeeze(1)
    rays = lambda: [x if ids is None else x[ids] for x in (p, s, direction, distance)]  # noqa: E731
    if not (use.occluders or use.terrain or use.voxels) or not occluders_supported(ctx, use):
        through = occluder_transmittance(ctx, use, *rays())
    else:
        through = occluders(ctx, use, *rays())
        _list(ctx, use.names()[1:])
    if ids is None:
        return out * through
    out[ids] = through * out[ids]
    return out


def chord_density(ctx, vol, rays, t0: Tensor, length: Tensor, ids: Tensor, steps: int) -> Tensor:
    """Σ density over `steps` equal segments' midpoints of the chunk's rays `ids` [m] from `t0` [m]
    over `length` [m] through volume `vol` (`renderer.labels.optical_thickness`'s sum) as one
    Dr.Jit kernel (`occluders_supported`'s conditions: the volume written in lanes, the plan's
    kernels); its evaluations counted as eager's are. -> [m]."""
    import drjit as dr

    s, row, lane, per_ray = _ray_lanes(rays, ids)
    density = crossing(vol, s, per_ray).density
    o, d, a, dt = row(rays.origins), row(rays.directions), lane(t0), lane(length / steps)

    def segment(k, state):  # the midpoint rounded as eager's addcmul rounds it
        t = a + (k + 0.5) * dt
        return [state[0] + density([dr.fma(t, d[c], o[c]) for c in range(3)], None)]

    total = lanes.fori(steps, [a * 0.0], segment)[0]
    dr.eval(total)
    dr.sync_thread()
    ctx.counts.density_evals += ids.shape[0] * steps
    vol.field.evals += ids.shape[0] * steps
    return lanes.tensor_of(total).to(t0.dtype)


def _list(ctx, names: list[str]) -> None:
    """Passes `names` in `stats`, run inside a kernel their caller times."""
    for name in names:
        with ctx.timer.section(name):
            pass


def occluder_lanes(ctx, use, s: Tensor, shared: dict | None = None) -> SimpleNamespace:
    """`shadow.occluder_transmittance`'s volumes and surfaces (`use.occluders`, `use.terrain`,
    `use.voxels`) for lanes of scenes `s` [n], inside a kernel its caller traces: `through(p, direction, distance,
    active=None)` the transmittance lane of rays from lanes `p` along `direction` (three each) up
    to `distance` (a tensor [n] or a lane, finite; inf: a sun, the sky), traced only where the Bool lane `active`
    (None: everywhere); `evals()` the lanes to evaluate with what it traced (the counts so far) and,
    after, `count()` each volume's evaluations into the render's stats. `shared`: what several
    calls for the same rays share (its ``per_ray``; each volume's crossing, the terrain's lanes and
    the voxels' walk, kept there as they are made)."""
    import drjit as dr
    from drjit.llvm import Int32

    shared = {} if shared is None else shared
    made = lambda key, make: shared[key] if key in shared else shared.setdefault(key, make())  # noqa: E731
    per_ray = made("per_ray", lambda: lanes.per_scene_lanes(s))
    solids = {j: made(j, lambda j=j: crossing(ctx.volumes[j], s, per_ray)) for j in use.occluders}
    grids = None if use.shadow.method != "grid" else {
        j: _grid_lanes(ctx, j, use.light, s, per_ray) for j in use.occluders if not ctx.volumes[j].plan.line_integral}
    terrain = made("terrain", lambda: terrain_lanes(ctx.terrain.p, lanes.lanes_inputs(s, per_ray), torch.float32)) if use.terrain else None
    blockers = SimpleNamespace(terrain=terrain, voxels=made("voxels", lambda: ctx.voxels.visibility_lanes(s, per_ray))
                               if use.voxels else None)
    evals = {j: dr.zeros(Int32, s.shape[0]) for j in use.occluders}

    def through(p, direction, distance, active=None):
        if isinstance(distance, Tensor):
            far = _far(distance, lambda x: lanes.lanes_of(x, lanes.floats_of))
        else:  # a lane of the kernel's own (a point light's), or inf (a sun)
            far = None if isinstance(distance, float) and math.isinf(distance) else distance
        if active is not None:  # a ray that is not traced reaches nowhere: nothing evaluated
            far = dr.select(active, math.inf if far is None else far, 0.0)
        out = _through_others(solids, use.occluders, blockers, p, direction, far, use.shadow, grids, evals)
        return out if not isinstance(out, float) else dr.full(type(p[0]), out, s.shape[0])

    return SimpleNamespace(through=through, evals=lambda: list(evals.values()), count=lambda: _count(ctx, evals))


def occluders(ctx, use, p: Tensor, s: Tensor, direction: Tensor, distance: Tensor) -> Tensor:
    """`occluder_lanes` as one Dr.Jit kernel (`occluders_supported` said yes): the same
    `_through_others` a kernel march's shadow rays take, from points `p` [n, 3] of scenes `s` [n]
    along `direction` [n, 3] up to `distance` [n] (inf: a sun, the sky). -> [n]; each volume's
    evaluations counted."""
    import drjit as dr

    if p.shape[0] == 0:
        return p.new_ones(0)
    set_drjit_threads()
    lane = lambda x: lanes.lanes_of(x, lanes.floats_of)  # noqa: E731
    k = occluder_lanes(ctx, use, s)
    through = k.through(lane(p), lane(direction), distance)
    dr.eval(through, k.evals())
    dr.sync_thread()
    k.count()
    return lanes.tensor_of(through).to(p.dtype)


def _far(distance: Tensor, lane):
    """A shadow ray's reach [n] as a lane (inf as 3e38), or None where every ray's is inf."""
    finite = torch.isfinite(distance)
    return None if not bool(finite.any()) else lane(torch.where(finite, distance, torch.full_like(distance, 3e38)))


def _pick(values: list, q):
    """values[q] per lane, `q` the Int32 lane of a piece (`values` one lane per piece)."""
    import drjit as dr

    out = values[0]
    for i in range(1, len(values)):
        out = dr.select(q == i, values[i], out)
    return out


def _next_piece(present: list, q):
    """The first piece after `q` (an Int32 lane) with a medium on the ray (`present`: a Bool lane
    a piece), or the number of pieces: none."""
    import drjit as dr
    from drjit.llvm import Int32

    out = dr.full(Int32, len(present), dr.width(q))
    for i in reversed(range(len(present))):
        out = dr.select((q < i) & present[i], Int32(i), out)
    return out


def _sample(m: SimpleNamespace, par: SimpleNamespace, count: int, p, t_sample, dt):
    """Member `m` (its volume, inputs and `_medium`) at lanes `p`, sampled at `t_sample` over a
    step `dt`: (σ_t, its source's three lanes, each of the `count` volumes' evaluations)."""
    import drjit as dr
    from drjit.llvm import Float, Int32

    med, mk, vol = m.medium, m.k, m.vol
    drop = None if par.lod is None or med.octaves is None else Int32(dr.floor(dr.log2(1.0 + t_sample * par.lod)))
    raw = med.density(p, None if drop is None else med.octaves - drop)
    sigma_t = mk.sigma_t * raw
    lit = (raw > par.threshold) & (dt > 0.0)
    width = dr.width(raw)
    dark = lambda: ([dr.zeros(Float, width) for _ in range(3)], [dr.zeros(Int32, width) for _ in range(count)])  # noqa: E731
    source, evals = dr.if_stmt((), lit, lambda: med.in_scatter(p, sigma_t, raw), dark)
    evals = list(evals)
    evals[vol.plan.index] = evals[vol.plan.index] + 1
    if vol.plan.emissive:  # σe = emission × density, then its colour map and the bloom, as `physical_medium` adds them
        source = tuple(source[c] + mk.emission[c] * raw for c in range(3))
    if vol.plan.emission_map is not None:
        source = tuple(a + b for a, b in zip(source, mk.emission_glow(mk.emission_map, p, raw)))
    if vol.plan.bloom is not None:
        source = tuple(a + b for a, b in zip(source, bloom_source(mk.bloom, p)))
    if vol.plan.sky_blend:  # last, as `physical_medium` blends the whole source
        source = sky_blend(source, mk.behind, sigma_t, mk.sky_blend, t_sample)
    return sigma_t, tuple(source), evals


def _body(k: SimpleNamespace, members: list, par: SimpleNamespace, st, count: int, shares: bool):
    """The loop body: one segment of `march.march`'s physical loop (``segments``, the render's
    integrator) in the ray's current piece, each member present sampled (its lighting under a branch
    where its density passes the threshold), then on to the next piece with a medium where the
    piece ends (`joint.march_joint`'s order)."""
    import drjit as dr
    from drjit.llvm import Bool, Float, Int32

    pieces = len(k.start)
    sample = lambda m, p, t_sample, dt: _sample(m, par, count, p, t_sample, dt)  # noqa: E731

    def body(t, q, piece_steps, trans, wsum, wt, median, steps, alive, truncated, first, *rest):
        evals, radiance = list(rest[:count]), list(rest[count:])
        start, end = _pick(k.start, q), _pick(k.end, q)
        dt = st.rule.length(t, end - start)
        alone = None if k.air is None else _pick(k.air.alone, q)
        if alone is not None:  # the air alone: smooth, in the atmosphere's own step count
            dt = dr.select(alone, lanes.divide(end - start, k.air.nodes), dt)
        if k.dither is not None:  # only a piece's first segment is dithered
            dt = dr.select(first, dt * k.dither, dt)
        dt = lanes.minimum(dt, end - t)
        t_sample = t + 0.5 * dt
        p = [dr.fma(t_sample, k.direction[c], k.origin[c]) for c in range(3)]  # rounded once, as eager's addcmul
        sigma, source, sigmas = dr.zeros(Float, dr.width(t)), [dr.zeros(Float, dr.width(t))] * 3, []
        for i, m in enumerate(members):
            if len(members) == 1 and k.air is None:  # (a piece has a medium: the one)
                sig, src, ev = sample(m, p, t_sample, dt)
            else:
                width = dr.width(t)
                none = lambda: (dr.zeros(Float, width), (dr.zeros(Float, width),) * 3,  # noqa: E731
                                [dr.zeros(Int32, width) for _ in range(count)])
                sig, src, ev = dr.if_stmt((), _pick(k.active[i], q), lambda m=m: sample(m, p, t_sample, dt), none)
            sigma, source = sigma + sig, [source[c] + src[c] for c in range(3)]
            evals = [e + x for e, x in zip(evals, ev)]
            sigmas.append(sig)
        if k.air is not None:  # its in-scatter (σ_t 0: its extinction is the factor below) where present
            inscatter, seen = _air_sample(k.air, _pick(k.air.on, q), t_sample, k.direction)
            source = [(source[c] + inscatter[c]) * seen[c] for c in range(3)]
        weight, seg_trans = WEIGHTS[st.integrator](sigma, dt)
        radiance = [r + trans * (x * weight) for r, x in zip(radiance, source + (sigmas if shares else []))]
        w, new_trans = trans * (1.0 - seg_trans), trans * seg_trans
        median = dr.select((trans > 0.5) & (new_trans <= 0.5), median_crossing(t, trans, sigma, dt), median)
        t_next, piece_steps = t + dt, piece_steps + 1
        inside = t_next < (end if k.stop is None else k.stop)
        going = new_trans >= par.min_transmittance if st.min_transmittance > 0 else dr.full(Bool, True, dr.width(t))
        limit = par.max_iterations if alone is None else dr.select(alone, Int32(k.air.nodes + 1), par.max_iterations)
        last = piece_steps >= limit
        truncated = truncated + dr.select(inside & going & last, Int32(1), Int32(0))
        done = ~inside | last
        after = _next_piece(k.present, q)
        q = dr.select(done, after, q)
        t_next = dr.select(done, _pick(k.start, q), t_next)
        return (t_next, q, dr.select(done, Int32(0), piece_steps), new_trans, wsum + w, wt + w * t_sample, median,
                steps + 1, going & (~done | (after < pieces)), truncated, done, *evals, *radiance)

    return body


__all__ = ["march", "march_look", "occluders", "occluders_supported", "supports", "surface_shadows"]
