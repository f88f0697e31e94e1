"""One march step as compiled kernels: the seeds' alpha look (`shading = "shader"`) over the
template's texture-noise cloud layer (`density.clouds`), marched in fixed-size wavefronts.

The generic `march` calls a medium closure that runs ~100 small eager ops per step (an fbm
octave is a dozen, the derivative light evaluates the fbm again, the look and the compositing add
their own); on a 2-core machine those ops, not the arithmetic, are the render. Here a step — the
sample point, its LOD, the cloud's fbm there and towards the light, the look's colour and fog,
alpha compositing, the step rule and the end tests — is pure functions of plain tensors
(`sample_density`, `light_density` on the lit samples only, `advance`, and `advance_sample`: the
one, then the next step's first, in one kernel), which torch.compile turns into fused C++ loops
over the rays: two compiled calls a step. The rays go through in wavefronts of at most `WAVEFRONT`
slots (a render's chunk): every `REFILL_EVERY` steps finished slots are written out and refilled
from the rays not started yet, or, once none wait, dropped when enough have finished, so the
kernels keep seeing full batches (shapes are dynamic: one compilation serves every size).

The eager `shader_steps` is the reference twin: it renders bitwise what the generic march renders
(tests/volume/test_fused.py; the LOD's dropped octaves are masked by `where`, which changes no
value); compiled, it matches the eager twin to ~1e-6, up to 4e-4 at a few pixels (inductor contracts multiply-adds, and
the texture's 8-bit filter turns an ulp of a coordinate into a 1/255 step at a few points). The
render takes this path under `render(..., compile=True)` where the plan says the volume is this
technique (docs/VOLUMES.md, "The fused march step"; figures in docs/SPEED.md).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor

from ..fields.clouds import cloud_density, cloud_fbm
from ..noise import lattice as noise
from ..ops.mathops import take_rows
from ..runtime.compilation import compiled
from ..runtime.threads import on_threads, torch_threads
from . import drjit_march
from .context import VolumeContext
from .march import MarchResult
from .march_spec import CloudLook, StepConfig

# slots marched at once: a render's whole chunk (`render.DEFAULT_CHUNK_RAYS`), so no chunk ends
# with a tail of rays marched in small wavefronts (61,440 left 4,096 rays of each chunk to 80
# steps of their own: a tenth of a template render)
WAVEFRONT = 1 << 16
# steps between refills: a refill gathers and scatters the whole state (a few eager ops)
REFILL_EVERY = 8
# with no rays left to start, finished slots are written out and dropped only once live ones fall
# below this share of the wavefront: a compaction costs about a step's kernel time
COMPACT_BELOW = 0.875
# rows of the slot state
_T, _TRANS, _WSUM, _WT, _MEDIAN, _STEPS, _ALIVE, _TRUNC, _EVALS, _RADIANCE = range(10)
_ROWS = _RADIANCE + 3
# rows of a slot's ray after origin, direction and sky (0-8): what stays constant along the march
# travels with the ray, not the state (the state's rows are written every step: each row passed
# through unchanged was a copy loop of its own in the kernel)
_T_END, _SPAN = 9, 10


def cloud_look(ctx: VolumeContext, vol) -> tuple[CloudLook, Tensor]:
    """The per-scene values of `vol` and its stacked texture tables, packed (`CloudLayer.packed`)."""
    layer, look, params = vol.field.inner, vol.params.shader, vol.params
    b, like = len(params), layer.shift
    zeros3 = like.new_zeros(b, 3)
    if vol.plan.lights:
        light = ctx.lights[vol.plan.lights[0].light]
        light_step, irradiance = look.light_offset[:, None] * light.direction, light.radiant
    else:
        light_step, irradiance = zeros3, zeros3
    heights = (vol.bounds.height_range(params.bounds.value) if look.ambient_top is not None
               else torch.stack([like.new_zeros(b), like.new_ones(b)], dim=1))
    cl = CloudLook(
        shift=layer.shift, bias=layer.p.bias, density_scale=layer.p.density_scale, light_step=light_step,
        irradiance=irradiance, light_scale=look.light_scale, ambient=look.ambient,
        ambient_top=look.ambient if look.ambient_top is None else look.ambient_top, heights=heights,
        color_lit=look.color_lit, color_dark=look.color_dark, alpha_scale=look.alpha_scale, fog=look.fog,
        base=noise.texture_rows(torch.arange(b, device=like.device), like.dtype))
    # one row more than the textures: dynamo's duck sizing ties equal sizes, and a table of 2**16
    # rows (one texture) as long as a full wavefront would specialise the kernels and recompile
    return cl, torch.cat([layer.packed, layer.packed[:1]])


def _count(t: Tensor, config: StepConfig) -> Tensor | None:
    """Octaves kept at distance `t` [N] (the template's LOD, `march.lod_drop`); None: all."""
    if config.lod_scale is None:
        return None
    return config.octaves - torch.floor(torch.log2(1.0 + t * config.lod_scale)).to(torch.int32)  # int64 halves the lanes


def _density(x: Tensor, y: Tensor, z: Tensor, count: Tensor | None, s: Tensor, look: CloudLook, packed: Tensor,
             scales: list[Tensor], config: StepConfig) -> Tensor:
    """`CloudLayer`'s density at points `x`, `y`, `z` [N] of scenes `s` [N], `count` [N] octaves
    kept there (`_count`)."""
    shift = look.shift[s]
    f = cloud_fbm(x - shift[:, 0], y - shift[:, 1], z - shift[:, 2], packed, look.base[s], count,
                  octaves=config.octaves, scales=scales)
    return cloud_density(f, y, look.bias[s], look.density_scale[s]).clamp_min(0.0)


class Sample(NamedTuple):
    """`sample_density`'s outputs. Separate tensors, not one stacked [5, N]: inductor computes a
    stack's rows in loops of their own, and the lit row evaluated the fbm a second time. `lit` is
    1.0 / 0.0, not bool: inductor's bool stores cost a third of the kernel's time."""

    density: Tensor  # [N]
    point: Tensor  # [3, N] the sample point, a row per coordinate
    lit: Tensor  # [N] 1.0: alive and over the density threshold
    # [N] int32 octaves kept at the sample (`_count`; None: all), handed on to `light_density`
    # rather than the sample's t, a row of the state: dynamo ties a view's base's sizes to the
    # others' (a first call's 12 lit samples to a 12-row state) and recompiled at the next step
    count: Tensor | None


def sample_density(state: Tensor, ray: Tensor, s: Tensor, look: CloudLook, packed: Tensor, scales: list[Tensor], *,
                   config: StepConfig) -> Sample:
    """A step's first kernel: each slot's sample point, its density and whether it is lit (alive
    and over `march.density_threshold`)."""
    t = state[_T]
    p = [torch.addcmul(ray[i], t, ray[3 + i]) for i in range(3)]
    count = _count(t, config)
    density = _density(*p, count, s, look, packed, scales, config)
    lit = (state[_ALIVE] > 0) & (density > config.threshold)
    return Sample(density, torch.stack(p), torch.where(lit, 1.0, 0.0), count)


def light_density(point: Tensor, count: Tensor | None, s: Tensor, lit: Tensor, look: CloudLook, packed: Tensor,
                  scales: list[Tensor], *, config: StepConfig) -> Tensor:
    """The second: the density `light_offset` towards the light from the points of the lit
    samples `lit` [k] (`point` [3, N] and `count` [N] of `sample_density`; `s` [N]) -> [k].
    Scattered to the slots outside: inductor runs a scatter (`index_put`) on one thread."""
    ss, ls = s[lit], look.light_step[s[lit]]
    return _density(*(point[c, lit] + ls[:, c] for c in range(3)), None if count is None else count[lit], ss, look,
                    packed, scales, config)


def advance(state: Tensor, ray: Tensor, s: Tensor, look: CloudLook, sample: Sample, ahead: Tensor, *,
            config: StepConfig) -> Tensor:
    """The third: the look's colour, alpha compositing, the step rule and the end tests -> the
    next state [_ROWS, N]. `ahead` [N]: `light_density` where lit (elsewhere unused)."""
    t, t_end, trans = state[_T], ray[_T_END], state[_TRANS]
    density, py, lit = sample.density, sample.point[1], sample.lit > 0
    alive = state[_ALIVE] > 0
    ambient = look.ambient[s]
    lin = [ambient[:, c] for c in range(3)]
    if config.graded:
        h, top = look.heights[s], look.ambient_top[s]
        w = ((py - h[:, 0]) / (h[:, 1] - h[:, 0])).clamp(0.0, 1.0)
        lin = [torch.lerp(lin[c], top[:, c], w) for c in range(3)]
    if config.light:
        dif = ((density - ahead) / look.light_scale[s]).clamp(0.0, 1.0)
        irradiance = look.irradiance[s]
        lin = [irradiance[:, c] * dif + lin[c] for c in range(3)]
    lit_color, dark_color = look.color_lit[s], look.color_dark[s]
    haze = 1.0 - torch.exp(-look.fog[s] * t * t)
    alpha = torch.where(lit, density * look.alpha_scale[s], 0.0)
    color = [torch.where(lit, torch.lerp(torch.lerp(lit_color[:, c], dark_color[:, c], density) * lin[c], ray[6 + c], haze), 0.0)
             for c in range(3)]
    # alpha_step, then march's accumulation
    seg = 1.0 - alpha
    weight = trans * (1.0 - seg)
    new_trans = trans * seg
    crossed = (trans > 0.5) & (new_trans <= 0.5)
    steps = state[_STEPS] + alive
    t_next = t + config.rule.length(t, ray[_SPAN])
    keep = t_next <= t_end
    if config.min_transmittance > 0:
        keep = keep & (new_trans >= config.min_transmittance)
    last = steps >= config.max_iterations
    return torch.stack([
        torch.where(alive, t_next, t), torch.where(alive, new_trans, trans),
        state[_WSUM] + weight, state[_WT] + weight * t, torch.where(crossed, t, state[_MEDIAN]), steps,
        (alive & keep & ~last).to(t.dtype), torch.where(alive, (keep & last).to(t.dtype), state[_TRUNC]),
        state[_EVALS] + alive + (lit if config.light else 0),
        *(state[_RADIANCE + c] + trans * (color[c] * alpha) for c in range(3)),
    ])


def advance_sample(state: Tensor, ray: Tensor, s: Tensor, look: CloudLook, packed: Tensor, scales: list[Tensor],
                   sample: Sample, ahead: Tensor, *, config: StepConfig) -> tuple[Tensor, Sample]:
    """`advance`, then the next step's `sample_density`, as one kernel: one pass over the slots
    and one compiled call fewer a step (each call costs ~30 µs of dynamo's guards and wrappers)."""
    state = advance(state, ray, s, look, sample, ahead, config=config)
    return state, sample_density(state, ray, s, look, packed, scales, config=config)


class Kernels(NamedTuple):
    """A step's kernels (`sample_density`, `light_density`, `advance`, `advance_sample`), eager or
    compiled."""

    sample: Callable
    light: Callable
    advance: Callable
    advance_sample: Callable


EAGER = Kernels(sample_density, light_density, advance, advance_sample)


def shader_steps(state: Tensor, ray: Tensor, s: Tensor, look: CloudLook, packed: Tensor, scales: list[Tensor], *,
                 count: int, config: StepConfig, kernels: Kernels = EAGER) -> Tensor:
    """`count` steps of every slot: `state` [_ROWS, N] (rows `_T` ...) -> the state after them.
    `ray` [11, N]: each slot's origin, direction, the sky behind it (a row per coordinate), the
    end of its march and its span (t1, t1 - t0: `_T_END`, `_SPAN`); `s`
    [N] its scene. A slot whose `_ALIVE` is 0 keeps its state. Per ray, the ops and their order
    are those of `march`, `shader_look.shader_medium` and `CloudLayer`. The light's density is
    taken only at the lit samples (about a tenth of a template's), gathered between the kernels:
    an eager op whose size depends on the data."""
    sample = kernels.sample(state, ray, s, look, packed, scales, config=config)
    # `ahead`, one buffer for the block: `advance` reads it only where the step is lit, which each
    # lit step writes anew (elsewhere it holds an earlier step's density: finite, unused)
    ahead = torch.zeros_like(state[_T])
    for k in range(count):
        if config.light:
            # a bool's nonzero: half a float's (45 against 100 µs on 65,536 slots, conversion included)
            lit = sample.lit.bool().nonzero().squeeze(1)
            if lit.shape[0]:
                # not a view (dynamo guards a view's base) and not one point (a compiled kernel would
                # specialise on it): either recompiles the kernel
                lit = lit.repeat(2) if lit.shape[0] == 1 else lit.clone()
                ahead.index_copy_(0, lit, kernels.light(sample.point, sample.count, s, lit, look, packed, scales,
                                                        config=config))
        if k + 1 < count:
            state, sample = kernels.advance_sample(state, ray, s, look, packed, scales, sample, ahead, config=config)
        else:
            state = kernels.advance(state, ray, s, look, sample, ahead, config=config)
    return state


@functools.cache
def compiled_steps(config: StepConfig, threads: int) -> Callable:
    """`shader_steps` with its kernels under torch.compile (each one graph per `config`, for
    every size) run on `threads` torch threads (the glue around them on the caller's)."""
    kernels = Kernels(*(on_threads(compiled(fn), threads) for fn in EAGER))
    return functools.partial(shader_steps, config=config, kernels=kernels)


def fused_march(steps, t0: Tensor, t1: Tensor, hit: Tensor, start: Tensor, ray: Tensor, s: Tensor, *,
                wavefront: int = WAVEFRONT, refill_every: int = REFILL_EVERY,
                compact_below: float = COMPACT_BELOW) -> tuple[MarchResult, Tensor]:
    """March the R rays where `hit` with `steps(state, ray, s, count)` (`shader_steps` with the
    rest bound) in wavefronts. `t0`, `t1`, `start` (the first sample's t) [R]; `hit` [R] bool; `ray`
    [9, R] (origin, direction, sky); `s` [R]. -> (the `march` result, density evaluations)."""
    ray = torch.cat([ray, t1[None], (t1 - t0)[None]])
    final = t0.new_zeros(_ROWS, t0.shape[0])
    final[_TRANS] = 1.0
    queue = hit.nonzero().squeeze(1)
    # each slot's ray index, state, ray rows and scene; gathers and scatters by index_select /
    # index_copy_ (`take_rows`: advanced indexing is 3-5x slower)
    slots, state, slot_ray, slot_s, taken = queue[:0], final[:, :0], ray[:, :0], s[:0], 0
    while True:
        room = min(wavefront - slots.shape[0], queue.shape[0] - taken)
        if room > 0:  # refill: fresh rays at their start
            new = queue[taken:taken + room]
            taken += room
            fresh = t0.new_zeros(_ROWS, room)
            fresh[_T] = take_rows(start, new)
            fresh[_TRANS], fresh[_ALIVE] = 1.0, 1.0
            slots, state = torch.cat([slots, new]), torch.cat([state, fresh], dim=1)
            slot_ray, slot_s = torch.cat([slot_ray, ray.index_select(1, new)], dim=1), torch.cat([slot_s, take_rows(s, new)])
        if slots.shape[0] == 0:
            break
        state = steps(state, slot_ray, slot_s, refill_every)
        alive = state[_ALIVE] > 0
        live = int(alive.sum())
        if live == slots.shape[0] or (taken == queue.shape[0] and live > compact_below * slots.shape[0]):
            continue  # nothing to refill and few finished: they ride along (a finished slot keeps its state)
        done = (~alive).nonzero().squeeze(1)
        final.index_copy_(1, take_rows(slots, done), state.index_select(1, done))
        keep = alive.nonzero().squeeze(1)
        if keep.shape[0] == 1:  # a finished slot rides along: one slot would recompile the kernels
            keep = torch.cat([keep, done[:1]])
        slots, state = take_rows(slots, keep), state.index_select(1, keep)
        slot_ray, slot_s = slot_ray.index_select(1, keep), take_rows(slot_s, keep)
    res = MarchResult(radiance=final[_RADIANCE:].T.contiguous(), transmittance=final[_TRANS], weight_sum=final[_WSUM],
                      weighted_t=final[_WT], median_t=final[_MEDIAN], steps=final[_STEPS].long(),
                      truncated=final[_TRUNC] > 0)
    return res, final[_EVALS].sum()


def march_fused(ctx: VolumeContext, vol, rays, background: Tensor, t0: Tensor, t1: Tensor, hit: Tensor, dither: Tensor | None, *,
                compiled: bool = True, drjit: bool = False) -> MarchResult:
    """The render's fused march of a volume the plan gave this backend (`plan.fused_march`) over a
    chunk's rays [n] (`run_march`'s fast path): one Dr.Jit kernel where `drjit` (the plan's
    backend), else the torch.compile kernels; `compiled` False runs the eager twin."""
    st = ctx.settings
    look, packed = cloud_look(ctx, vol)
    octaves = int(vol.field.inner.p.octaves)
    scales = noise.folded_scales(octaves, dtype=t0.dtype, device=t0.device)
    config = StepConfig(rule=st.rule, octaves=octaves, lod_scale=st.lod_scale, threshold=float(st.density_threshold),
                        min_transmittance=float(st.min_transmittance), max_iterations=st.rule.max_iterations,
                        light=bool(vol.plan.lights), graded=vol.params.shader.ambient_top is not None)
    start = t0
    if dither is not None:  # the template's absolute offset, or a fraction of the first step
        start = t0 + (dither if st.dither == "sin" else dither * st.rule.length(t0, t1 - t0))
    ray = torch.cat([rays.origins.T, rays.directions.T, background.T])
    if compiled and drjit:
        res, evals = drjit_march.march(t0, t1, hit, start, ray, rays.scene_index, look, packed, scales, config=config)
    else:
        # compiled: the kernels on the render's threads, the glue between them on one (`threads`)
        threads = torch.get_num_threads()
        kernel = compiled_steps(config, threads) if compiled else functools.partial(shader_steps, config=config)
        with torch_threads(1 if compiled else threads):
            res, evals = fused_march(lambda state, r, s, n: kernel(state, r, s, look, packed, scales, count=n), t0, t1,
                                     hit, start, ray, rays.scene_index, wavefront=WAVEFRONT, refill_every=REFILL_EVERY,
                                     compact_below=COMPACT_BELOW)
    ctx.counts.density_evals += int(evals)
    vol.field.evals += int(evals)
    return res
