"""The template's fused march (`volume.fused`) as one Dr.Jit kernel per chunk: torch tensors in
and out, the same per-ray ops as the eager twin `fused.shader_steps`.

`fused`'s torch.compile kernels are two calls a step over a wavefront, with eager glue between
them (the lit samples' `nonzero`, refills, compaction): ~1,700 calls at 1280×720, each a parallel
region that wakes OpenMP's sleeping threads, and a pass over the wavefront's state in memory at
every step. Dr.Jit (the LLVM backend, https://drjit.readthedocs.io) traces the whole march, a loop
per ray (`drjit.while_loop`, symbolic) with the light's fbm under a per-ray branch
(`drjit.if_stmt`), into one vectorised kernel: a ray's state stays in registers until its march
ends, and the kernel is one launch on Dr.Jit's own thread pool. Its texture-noise fbm alone is
1.6-1.9× inductor's fused kernel on the same points, bitwise the eager values
(tests/volume/test_drjit_march.py); the march takes about half the compiled torch render's time
(docs/SPEED.md).

The kernel is built once per structure (octaves, light, height-graded ambient, LOD on or off, step
placement, a transmittance cut-off or not) and cached by Dr.Jit on disk: settings that are
numbers (threshold, step sizes, LOD scale, the step limit, per-scene values) are the kernel's
parameters (`drjit.opaque`), not constants baked into it, so a dataset whose scenes draw them at
random compiles nothing more.

Chosen by the plan (`renderer.plan.march_backend`) for float32 renders on the CPU where `available`; elsewhere the
torch.compile kernels run. `TORCHVOL_DRJIT=0` turns it off. The kernel runs on
`threads.kernel_threads`: a render whose every march is this kernel runs its torch work on one
thread and the kernel on its caller's count (the plan's `threads`, "glue_on_one_thread").
"""

from __future__ import annotations

import os
from collections.abc import Callable
from types import SimpleNamespace
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from ..fields.clouds import cloud_density, cloud_fbm
from ..ops import lanes
from ..runtime.threads import set_drjit_threads
from .march import MarchResult

if TYPE_CHECKING:
    from .march_spec import CloudLook, StepConfig

OPT_OUT = "TORCHVOL_DRJIT"
# whether this process may use Dr.Jit: None until the first `available` probes it. A child forked
# after its parent started Dr.Jit (a DataLoader worker) uses it too: its kernels run there, the same
# bytes (tests/volume/test_kernel_march.py), since a sample's bytes must not depend on the workers
_USABLE: dict[str, bool | None] = {"usable": None}


def _probe() -> bool:
    try:
        import drjit as dr
    except ImportError:
        return False
    return bool(dr.has_backend(dr.JitBackend.LLVM))


def available(like: Tensor) -> bool:
    """Whether the Dr.Jit march can render with `like` (a tensor of the render's dtype and device):
    float32 on the CPU, `drjit` importable with its LLVM backend (it needs libLLVM) and
    `TORCHVOL_DRJIT` not "0"."""
    if like.dtype != torch.float32 or like.device.type != "cpu" or os.environ.get(OPT_OUT) == "0":
        return False
    if _USABLE["usable"] is None:
        _USABLE["usable"] = _probe()
    return bool(_USABLE["usable"])


def _floats(t: Tensor):
    from drjit.llvm import Float

    return Float(t.detach().to(torch.float32).contiguous().numpy())


def march(t0: Tensor, t1: Tensor, hit: Tensor, start: Tensor, ray: Tensor, s: Tensor, look: CloudLook, packed: Tensor,
          scales: list[Tensor], *, config: StepConfig) -> tuple[MarchResult, Tensor]:
    """`fused.fused_march` over `fused.shader_steps` as one Dr.Jit kernel: the R rays where `hit`
    [R] bool, from `start` [R] to `t1` [R] (`t0` [R] the entry); `ray` [9, R] origin, direction,
    sky (a row per coordinate); `s` [R] scenes; `look`, `packed` [M] and `scales` as
    `fused.cloud_look` and `noise.folded_scales` give them. -> (the `march` result, density
    evaluations (0-dim int64))."""
    import drjit as dr
    from drjit.llvm import Bool, Float, Int32, UInt32

    idx = hit.nonzero().squeeze(1)
    result = MarchResult.empty(t0, 3)
    if idx.shape[0] == 0:
        return result, torch.zeros((), dtype=torch.long)
    set_drjit_threads()

    def rays(x: Tensor):  # [R] -> the hit rays' Float
        return _floats(x.index_select(0, idx))

    origin, direction, sky = ([rays(ray[row + c]) for c in range(3)] for row in (0, 3, 6))
    k = SimpleNamespace(origin=origin, direction=direction, sky=sky, t_end=rays(t1), span=rays(t1 - t0))
    k.__dict__.update(_per_ray_look(look, UInt32(s.index_select(0, idx).to(torch.int32).numpy())))
    k.table = Int32(packed.to(torch.int32).numpy())
    k.__dict__.update(_kernel_parameters(config, scales))
    n = dr.width(k.t_end)
    zero = dr.zeros(Float, n)
    state = (rays(start), dr.full(Float, 1.0, n), zero, zero, zero, dr.zeros(Int32, n), dr.full(Bool, True, n),
             dr.full(Bool, False, n), dr.zeros(Int32, n), zero, zero, zero)
    out = dr.while_loop(state, lambda *st: st[6], _march_body(k, config), mode="symbolic")
    dr.eval(out)
    dr.sync_thread()
    _, trans, wsum, wt, median, steps, _, truncated, evals, *radiance = (torch.from_numpy(np.array(v)) for v in out)
    result.radiance.index_copy_(0, idx, torch.stack(radiance, 1))
    for name, value in (("transmittance", trans), ("weight_sum", wsum), ("weighted_t", wt), ("median_t", median),
                        ("steps", steps.long()), ("truncated", truncated)):
        getattr(result, name).index_copy_(0, idx, value)
    return result, evals.long().sum()


def _per_ray_look(look: CloudLook, scene) -> dict:
    """Each field of `look` (per scene, (B,) or (B, C)) gathered to the rays of UInt32 `scene`
    [n]: a Float, or a list of C Floats; `base` an Int32."""
    import drjit as dr
    from drjit.llvm import Float, Int32

    def per_ray(value: Tensor):  # per scene (B,) or (B, C) -> the rays' Float, or a list of C
        if value.ndim == 1:
            return dr.gather(Float, _floats(value), scene)
        return [dr.gather(Float, _floats(value[:, c]), scene) for c in range(value.shape[1])]

    values = {name: per_ray(getattr(look, name)) for name in look._fields if name != "base"}
    values["base"] = dr.gather(Int32, Int32(look.base.to(torch.int32).numpy()), scene)
    return values


def _kernel_parameters(config: StepConfig, scales: list[Tensor]) -> dict:
    """The numbers of `config` and the octave `scales` as the kernel's parameters, not its
    constants (one kernel whatever a dataset draws)."""
    import drjit as dr
    from drjit.llvm import Float, Int32

    param = lambda v: dr.opaque(Float, float(v))
    values = {"octave_scales": [param(c) for c in scales], "threshold": param(config.threshold),
              "max_iterations": dr.opaque(Int32, config.max_iterations)}
    values["lod_scale"] = None if config.lod_scale is None else param(config.lod_scale)
    values["min_transmittance"] = param(config.min_transmittance)
    return values


def _march_body(k: SimpleNamespace, config: StepConfig) -> Callable:
    """The loop body of the Dr.Jit march over the kernel's inputs `k` (`march`'s rays, per-ray
    look and parameters): `fused.sample_density` then `fused.advance` for one ray."""
    import drjit as dr
    from drjit.llvm import Int32

    def density(x, y, z, count):
        f = cloud_fbm(x - k.shift[0], y - k.shift[1], z - k.shift[2], k.table, k.base, count, octaves=config.octaves,
                      scales=k.octave_scales)
        return lanes.clamp_min(cloud_density(f, y, k.bias, k.density_scale), 0.0)

    def body(t, trans, wsum, wt, median, steps, alive, truncated, evals, red, green, blue):
        # the loop runs only alive rays
        p = [k.origin[c] + t * k.direction[c] for c in range(3)]
        count = None if k.lod_scale is None else config.octaves - Int32(dr.floor(dr.log2(1.0 + t * k.lod_scale)))
        rho = density(*p, count)
        lit = rho > k.threshold
        lin = _sample_light(k, config, density, p, count, rho, lit)
        haze = 1.0 - dr.exp(-k.fog * t * t)
        alpha = dr.select(lit, rho * k.alpha_scale, 0.0)
        color = [dr.select(lit, lanes.lerp(lanes.lerp(k.color_lit[c], k.color_dark[c], rho) * lin[c], k.sky[c], haze), 0.0)
                 for c in range(3)]
        seg = 1.0 - alpha  # the eager step's alpha_step, op for op
        weight, new_trans = trans * (1.0 - seg), trans * seg
        crossed = (trans > 0.5) & (new_trans <= 0.5)
        steps = steps + 1
        t_next = t + config.rule.length(t, k.span)  # the eager rule itself, traced (`ops.lanes`)
        keep = t_next <= k.t_end
        if config.min_transmittance > 0:
            keep = keep & (new_trans >= k.min_transmittance)
        last = steps >= k.max_iterations
        radiance = (red, green, blue)
        return (t_next, new_trans, wsum + weight, wt + weight * t, dr.select(crossed, t, median), steps,
                keep & ~last, keep & last, evals + 1 + (Int32(lit) if config.light else 0),
                *(radiance[c] + trans * (color[c] * alpha) for c in range(3)))

    return body


def _sample_light(k: SimpleNamespace, config: StepConfig, density: Callable, p: list, count, rho, lit) -> list:
    """The light at points `p` (three Floats) of density `rho`: the ambient, height-graded where
    `config.graded`, plus the derivative light where `config.light` (its density looked up only
    where `lit`). -> three Floats."""
    import drjit as dr
    from drjit.llvm import Float

    lin = list(k.ambient)
    if config.graded:
        w = lanes.clamp((p[1] - k.heights[0]) / (k.heights[1] - k.heights[0]), 0.0, 1.0)
        lin = [lanes.lerp(lin[c], k.ambient_top[c], w) for c in range(3)]
    if config.light:
        step = k.light_step
        ahead = dr.if_stmt((p[0], p[1], p[2], count), lit,
                           lambda x, y, z, n: density(x + step[0], y + step[1], z + step[2], n),
                           lambda x, y, z, n: dr.zeros(Float, dr.width(x)))
        dif = lanes.clamp((rho - ahead) / k.light_scale, 0.0, 1.0)
        lin = [k.irradiance[c] * dif + lin[c] for c in range(3)]
    return lin
