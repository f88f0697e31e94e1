"""The physical march of one volume as one Dr.Jit kernel per chunk: a loop per ray (its state in
registers until its march ends), the lights' shadow marches and the sky light's visibility march
under a per-sample branch where the density passes the threshold, the step rule, dither,
early termination and the depth statistics inside it.

One source: every per-sample formula here is the eager renderer's own function, written in lanes
(`ops.lanes`) and traced here with Dr.Jit arrays: the density (its kind's ``lanes`` capability in
`fields.DENSITIES`: constant, exponential, value-noise fbm), the edge fade (`fields.edge.faded`
over the bounds' ``lanes`` depth), the shadow rays' exits and segments (the bounds' ``lanes``
interval, `volume.shadow.shadow_segments`), a point light's falloff (`light.lights.point_lanes`)
and phase (`light.phase`'s ``lanes``), the multiple-scattering octaves
(`volume.multiple.octave_weights`), the step rule (`march.StepRule.length`), the Frostbite step
(`integrate.frostbite_weight`) and the median (`march.median_crossing`). What is constant along a
ray is computed by the eager code itself before the kernel runs: the suns' phase responses
(`physical.light_responses`), the dither, entry and exit. The eager march (`compile="off"`) is the
reference the kernel is held to (tests/volume/test_kernel_march.py).

`supports` says which volumes it renders (the plan asks once); the others run eagerly. Numbers a
dataset draws per scene are the kernel's inputs, and the settings that are numbers are its
parameters (`drjit.opaque`), so one kernel serves a whole dataset; Dr.Jit caches it on disk.
"""

from __future__ import annotations

from collections.abc import Callable
from types import SimpleNamespace

import numpy as np
import torch
from torch import Tensor

from ..fields import DENSITIES
from ..fields.base import DENSITY_MAX
from ..fields.edge import EdgeField, faded
from ..geometry.bounds import BOUNDS
from ..light.lights import point_lanes
from ..ops import lanes
from ..runtime.threads import kernel_threads
from ..schema.batch import take
from .emission import EMISSION_MAPS, bloom_lanes, bloom_source
from .integrate import frostbite_weight
from .march import MarchResult, median_crossing
from .multiple import octave_weights
from .physical import light_responses
from .shadow import shadow_segments


def supports(batch, vol, uses, settings) -> str | None:
    """Why the kernel cannot render volume `vol` (its `Stacked` parameters) of `batch` with its
    light passes `uses`, or None where it can: a density written in lanes (constant, exponential,
    value-noise fbm of either hash) in bounds written in lanes (sphere, box, slab), physically
    shaded with the Frostbite integrator, lit by suns and point lights with marched shadows
    through it alone, ungraded sky light, emission, its colour map and bloom; `settings` the render's
    `MarchSettings`."""
    checks = [
        (_has_lanes(vol), f"the {vol.density.kind} density"),
        ("lanes" in BOUNDS[vol.bounds.kind].caps, f"{vol.bounds.kind} bounds"),
        (vol.shading == "physical", f"the {vol.shading} shading"),
        (batch.atmosphere is None, "the [atmosphere]"),
        (settings.integrator == "frostbite" and settings.tolerance is None, "the march settings"),
        (vol.sky_blend is None, "a sky blend"),
        (vol.ambient is None or vol.ambient.top is None, "a graded ambient"),
        (all(batch.lights[u.light].kind in ("sun", "point") for u in uses), "a light other than a sun or a point"),
        (all(u.shadow is None or (u.shadow.method == "march" and not (u.occluders or u.terrain or u.voxels)) for u in uses),
         "shadows through other volumes or surfaces"),
        (batch.terrain is None and batch.voxels is None, "surfaces"),
    ]
    return next((why for ok, why in checks if not ok), None)


def _has_lanes(vol) -> bool:
    """Whether the volume's density kind is written in lanes for this variant (`fields.DENSITIES`)."""
    kind = DENSITIES[vol.density.kind].caps.get("lanes")
    return kind is not None and (len(kind) < 3 or kind[2](vol))


def _floats(t: Tensor):
    from drjit.llvm import Float

    return Float(t.detach().to(torch.float32).contiguous().cpu().numpy())


def _lanes_of(value: Tensor, gather):
    """Per-ray lanes of a per-ray tensor [n] or [n, C] (a list of C lanes)."""
    return gather(value) if value.ndim == 1 else [gather(value[:, c]) for c in range(value.shape[1])]


def _field_inputs(vol, s: Tensor, per_ray) -> SimpleNamespace:
    """What the volume's density takes per lane, for points of scenes `s` [n] (`per_ray`: per
    scene -> per lane): its kind's lanes inputs (`fields.DENSITIES`' ``lanes``), the bounds', the edge's."""
    import drjit as dr
    from drjit.llvm import Float, Int32

    inner, edge = _inner_and_edge(vol)
    inputs, density = DENSITIES[vol.params.density.kind].caps["lanes"][:2]
    to = SimpleNamespace(per_lane=per_ray, scene=s.cpu(), ints=lambda t: Int32(t.to(torch.int32).numpy()),
                         floats=lambda t: Float(t.to(torch.float32).numpy()), number=lambda c: dr.opaque(Float, float(c)))
    bounds = vol.params.bounds.value
    return SimpleNamespace(
        field=inputs(inner, to), field_density=density,
        bounds=SimpleNamespace(**{name: per_ray(getattr(bounds, name)) for name in type(bounds.models[0]).model_fields}),
        edge=None if edge is None else SimpleNamespace(width=per_ray(edge.width),
                                                       base=None if edge.base is None else per_ray(edge.base)))


def density_kernel(vol, points: Tensor) -> Callable[[], Tensor]:
    """The volume's density alone at `points` [N, 3] of scene 0, as one Dr.Jit kernel: the march's
    floor (`torchvol bench speed`: what the march would cost if nothing but its density did).
    -> a function that evaluates it once, returning [N]."""
    import drjit as dr

    s = torch.zeros(points.shape[0], dtype=torch.long)
    k = _field_inputs(vol, s, lambda x: _lanes_of(take(x, s), _floats))
    medium = _medium(k, vol, _parameters(vol, None))
    p = _lanes_of(points, _floats)

    def run() -> Tensor:
        threads = kernel_threads()
        if dr.thread_count() != threads:
            dr.set_thread_count(threads)
        out = medium.density(p, None)
        dr.eval(out)
        dr.sync_thread()
        return torch.from_numpy(np.array(out))

    return run


def _inputs(ctx, vol, rays, t0: Tensor, t1: Tensor, dither: Tensor | None, idx: Tensor) -> SimpleNamespace:
    """The kernel's per-ray inputs for the rays `idx` [n], computed by the eager code: rays, what
    the field, bounds, lights and sky take per ray, the lights' phase responses."""
    s = rays.scene_index.index_select(0, idx)
    o, d = rays.origins.index_select(0, idx), rays.directions.index_select(0, idx)
    lane = lambda x: _lanes_of(x, _floats)  # noqa: E731
    per_ray = lambda x: lane(take(x, s))  # noqa: E731  per scene -> per ray
    k = SimpleNamespace(origin=lane(o), direction=lane(d), t_start=lane(t0.index_select(0, idx)),
                        t_end=lane(t1.index_select(0, idx)), dither=None if dither is None else lane(dither.index_select(0, idx)))
    k.span = k.t_end - k.t_start
    k.__dict__.update(vars(_field_inputs(vol, s, per_ray)))
    k.sigma_t, k.albedo = per_ray(vol.params.sigma_t), per_ray(vol.params.albedo)
    responses = light_responses(ctx, vol, d, s)
    k.lights = []
    for use in vol.plan.lights:
        light, resp = ctx.lights[use.light], responses[use.light]  # [n, 3] or per octave [n, K, 3]; None: a point light
        if resp is None:  # its θ changes along the ray: the phase is traced per sample
            k.lights.append(SimpleNamespace(response=None, position=per_ray(light.params.position),
                                            radiant=per_ray(light.radiant), shadow=use.shadow))
            continue
        resp = [resp] if resp.ndim == 2 else list(resp.unbind(1))
        k.lights.append(SimpleNamespace(response=[lane(r) for r in resp], direction=per_ray(light.direction),
                                        shadow=use.shadow))
    if any(light.response is None for light in k.lights):
        inputs, k.phase = vol.phase.caps["lanes"]
        k.phase_params = inputs(vol.params.phase.value, SimpleNamespace(per_lane=per_ray))
        ms = vol.params.multiple_scattering
        k.octave_scales = [] if not vol.plan.multiple else [(per_ray(ms.a**i), per_ray(ms.c**i)) for i in range(1, ms.octaves)]
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
        k.ambient = lane(take(vol.ambient_bottom, s))
        k.ambient_direction = per_ray(torch.nn.functional.normalize(amb.direction, dim=1))
        k.ambient_sigma = per_ray(amb.sigma_scale * vol.params.sigma_t)
        k.ambient_steps = amb.steps
    return k


def march(ctx, vol, rays, background: Tensor | None, t0: Tensor, t1: Tensor, hit: Tensor,
          dither: Tensor | None) -> tuple[MarchResult, int]:
    """The fixed march of physical volume `vol` (`supports` said yes) for a chunk's `rays` [R]
    through [t0, t1] [R] where `hit` [R], `dither` [R] the first segment's fraction or None, as
    one Dr.Jit kernel (`background`, the sky behind [R, 3], is not part of a physical medium's
    source without `sky_blend`, which `supports` leaves to eager). -> (`march.march`'s result,
    density evaluations)."""
    import drjit as dr
    from drjit.llvm import Bool, Float, Int32

    idx = hit.nonzero().squeeze(1)
    result = MarchResult.empty(t0, 3)
    if idx.shape[0] == 0:
        return result, 0
    threads = kernel_threads()
    if dr.thread_count() != threads:
        dr.set_thread_count(threads)
    k = _inputs(ctx, vol, rays, t0, t1, dither, idx)
    n = dr.width(k.t_start)
    zero = dr.zeros(Float, n)
    state = (k.t_start, dr.full(Float, 1.0, n), zero, zero, zero, dr.zeros(Int32, n), dr.full(Bool, True, n),
             dr.full(Bool, False, n), dr.full(Bool, True, n), dr.zeros(Int32, n), zero, zero, zero)
    out = dr.while_loop(state, lambda *s: s[6], _body(k, vol, ctx.settings), mode="symbolic")
    dr.eval(out)
    dr.sync_thread()
    _, trans, wsum, wt, median, steps, _, truncated, _, evals, *radiance = (torch.from_numpy(np.array(v)) for v in out)
    result.radiance.index_copy_(0, idx, torch.stack(radiance, 1).to(t0.dtype))
    for name, value in (("transmittance", trans), ("weight_sum", wsum), ("weighted_t", wt), ("median_t", median),
                        ("steps", steps.long()), ("truncated", truncated)):
        target = getattr(result, name)
        target.index_copy_(0, idx, value.to(target.dtype))
    return result, int(evals.long().sum())


def _parameters(vol, st) -> SimpleNamespace:
    """The settings `st` (`MarchSettings`; None: none, the density alone) that are numbers as the
    kernel's parameters (`drjit.opaque`: one kernel for any value), the octave count and scales."""
    import drjit as dr
    from drjit.llvm import Float, Int32

    if st is None:  # the density alone
        return SimpleNamespace()
    return SimpleNamespace(
        threshold=dr.opaque(Float, st.density_threshold), reach=dr.opaque(Float, min(vol.plan.reach, 3e38)),
        lod=None if st.lod_scale is None else dr.opaque(Float, st.lod_scale),
        min_transmittance=dr.opaque(Float, st.min_transmittance), max_iterations=dr.opaque(Int32, st.rule.max_iterations))


def _medium(k: SimpleNamespace, vol, par: SimpleNamespace) -> SimpleNamespace:
    """The per-sample functions of the volume over the kernel's inputs `k` and parameters `par`:
    density(p, count), transmittance(p, direction, sigma_scale, shadow), in_scatter(p, sigma_t)."""
    import drjit as dr
    from drjit.llvm import Float

    interval, depth_in = vol.bounds.caps["lanes"]

    def density(p, count):
        """The density at lanes `p` (three), `count` octaves kept or None: the field clamped at 0,
        faded at the edge and capped, as `renderer.stats.CountedField` reads it."""
        raw = lanes.clamp_min(k.field_density(k.field, p, count), 0.0)
        if k.edge is not None:
            depth = depth_in(k.bounds, p)
            if k.edge.base is not None:
                depth = lanes.minimum(depth, p[1] - k.edge.base)
            raw = faded(raw, depth, k.edge.width)
        return lanes.clamp_max(raw, DENSITY_MAX)

    def transmittance(p, direction, sigma_scale, shadow, distance=None):
        """From lanes `p` along `direction` (three lanes) out of the bounds or to the light at
        `distance` (None: a sun), σ_t = `sigma_scale` × density, over `shadow`'s segments
        (`shadow.shadow_transmittance`'s march)."""
        exit_t = lanes.clamp(interval(k.bounds, p, direction)[1], 0.0, par.reach)
        if distance is not None:
            exit_t = lanes.minimum(exit_t, distance)
        tau = dr.zeros(Float, dr.width(exit_t))
        for mid, length in shadow_segments(exit_t, steps=shadow.steps, growth=shadow.growth, first_step=shadow.first_step):
            tau = tau + sigma_scale * density([p[c] + mid * direction[c] for c in range(3)], None) * length
        return lanes.exp(-tau)

    def in_scatter(p, sigma_t):
        """Σ over the lights of σs·p(θ)·E·T_light (octaves summed), plus σs·L_amb·V: three lanes
        (`physical.in_scatter`'s terms, in its order)."""
        sigma_s = k.albedo * sigma_t
        out = [dr.zeros(Float, dr.width(sigma_t)) for _ in range(3)]
        for light in k.lights:
            response, direction, distance = light.response, getattr(light, "direction", None), None
            if response is None:  # a point light: `physical.response` at this sample
                direction, irradiance, distance = point_lanes(light.position, light.radiant, p)
                cos = k.direction[0] * direction[0] + k.direction[1] * direction[1] + k.direction[2] * direction[2]
                response = [[e * k.phase(k.phase_params, cos, 1.0) for e in irradiance]]
                response += [[e * (a * k.phase(k.phase_params, cos, c)) for e in irradiance] for a, c in k.octave_scales]
            trans = None if light.shadow is None else transmittance(p, direction, k.sigma_t, light.shadow, distance)
            weights = octave_weights(sigma_s, trans, k.exponents if vol.plan.multiple else [])
            out = [out[c] + sum((response[i][c] * weights[i] for i in range(1, len(weights))),
                                response[0][c] * weights[0]) for c in range(3)]
        if vol.plan.ambient:
            amb = [k.ambient[c] * sigma_s for c in range(3)]
            if vol.plan.ambient_sky is not None:
                v = transmittance(p, k.ambient_direction, k.ambient_sigma,
                                  SimpleNamespace(steps=k.ambient_steps, growth=1.0, first_step=None))
                amb = [a * v for a in amb]
            out = [out[c] + amb[c] for c in range(3)]
        return out

    return SimpleNamespace(density=density, transmittance=transmittance, in_scatter=in_scatter)


def _body(k: SimpleNamespace, vol, st):
    """The loop body: one segment of `march.march`'s physical loop (``segments``, the Frostbite
    step) for a ray still going, its lighting under a branch where the density passes the threshold."""
    import drjit as dr
    from drjit.llvm import Bool, Float, Int32

    par = _parameters(vol, st)
    medium = _medium(k, vol, par)
    octaves = getattr(k.field, "octaves", None)  # LOD cuts a sum of octaves short
    lit_evals = sum(light.shadow.steps for light in k.lights if light.shadow is not None)
    lit_evals += k.ambient_steps if vol.plan.ambient and vol.plan.ambient_sky is not None else 0

    def body(t, trans, wsum, wt, median, steps, alive, truncated, first, evals, red, green, blue):
        dt = st.rule.length(t, k.span)
        if k.dither is not None:  # only a ray's first segment is dithered
            dt = dr.select(first, dt * k.dither, dt)
        dt = lanes.minimum(dt, k.t_end - t)
        t_sample = t + 0.5 * dt
        p = [k.origin[c] + t_sample * k.direction[c] for c in range(3)]
        count = None if par.lod is None or octaves is None else octaves - Int32(dr.floor(dr.log2(1.0 + t_sample * par.lod)))
        raw = medium.density(p, count)
        sigma_t = k.sigma_t * raw
        lit = (raw > par.threshold) & (dt > 0.0)
        source = dr.if_stmt((p[0], p[1], p[2], sigma_t), lit, lambda x, y, z, sg: tuple(medium.in_scatter([x, y, z], sg)),
                            lambda x, y, z, sg: (dr.zeros(Float, dr.width(x)),) * 3)
        if vol.plan.emissive:  # σe = emission × density, then its colour map and the bloom, as `physical_medium` adds them
            source = tuple(source[c] + k.emission[c] * raw for c in range(3))
        if vol.plan.emission_map is not None:
            source = tuple(a + b for a, b in zip(source, k.emission_glow(k.emission_map, p, raw)))
        if vol.plan.bloom is not None:
            source = tuple(a + b for a, b in zip(source, bloom_source(k.bloom, p)))
        weight, seg_trans = frostbite_weight(sigma_t, dt)
        radiance = tuple(r + trans * (source[c] * weight) for c, r in enumerate((red, green, blue)))
        w, new_trans = trans * (1.0 - seg_trans), trans * seg_trans
        median = dr.select((trans > 0.5) & (new_trans <= 0.5), median_crossing(t, trans, sigma_t, dt), median)
        steps, t_next = steps + 1, t + dt
        keep = t_next < k.t_end
        if st.min_transmittance > 0:
            keep = keep & (new_trans >= par.min_transmittance)
        last = steps >= par.max_iterations
        return (t_next, new_trans, wsum + w, wt + w * t_sample, median, steps, keep & ~last, keep & last,
                dr.full(Bool, False, dr.width(t)), evals + 1 + dr.select(lit, Int32(lit_evals), Int32(0)), *radiance)

    return body


def _inner_and_edge(vol):
    """The volume's density field and its `Edge` tables (None: no edge fade) under its counted field."""
    field = vol.field.inner
    return (field.inner, field.edge) if isinstance(field, EdgeField) else (field, None)


__all__ = ["density_kernel", "march", "supports"]
