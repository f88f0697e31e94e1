"""`torchvol bench speed`: where a render's time goes against its peers, in one run (docs/SPEED.md).

A profile, then four tables, every figure a median of `repeat` runs measured in this one run, so ratios hold on
any machine (absolute times only on a quiet one):

0. Where an eager render's time goes: torch.profiler's top ops (self CPU time) of `cloud-puff`
   (physical, table-hash value-noise fbm) and `template-clouds` (texture noise) at 64×64.
1. `template-clouds` on Mesa llvmpipe (the same GLSL template, `torchvol.measure.glsl`) against
   torchvol eager and by default (its march one Dr.Jit kernel, `volume.kernel_march.march_look`),
   and a physical cloud (`cloud-puff`) with the table hash and the arithmetic hash
   (`torchvol.noise.fast`), eager and by default; each row with its density evaluations per second.
2. The floor: density evaluations per second of each render's noise alone on the same points
   (cloud-puff's value-noise fbm: table hash eager, arithmetic hash eager and in Dr.Jit; the
   template's texture-noise fbm eager and in Dr.Jit); each render row's time over its floor, the
   fastest of these kernels run beside each of the row's renders.
3. Generation: samples/s of bundled recipes at 128×128 with 1 and 2 workers (`generate`, the
   full path: sampling, batched render, encoding, writes; worker runs include process start-up).
4. The loaded-machine slowdown: a render in a fresh process alone and while one
   ``python -c "while True: pass"`` keeps a core busy, per thread count and OpenMP wait policy.
5. The heap: renders in fresh processes with glibc's malloc as `torchvol.runtime.heap` sets it and left
   alone; seconds, page faults and system time per render.

A kernel's build is excluded from the steady-state rows and reported on its own (first call).
"""

from __future__ import annotations

import compileall
import contextlib
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path
from typing import Callable, NamedTuple, Sequence

import torch

from ..fields.clouds import cloud_fbm
from ..noise import fast as fastnoise
from ..noise import lattice as noise
from ..renderer.executor import render
from ..runtime import compilation
from ..runtime.threads import torch_threads
from ..scene.model import preset, preset_names

ROOT = Path(__file__).resolve().parents[2]
RECIPES = sorted(p.stem for p in (ROOT / "datasets").glob("*.toml"))
TEMPLATE_SIZES = ((640, 360), (1280, 720))
PARTS = ("profile", "render", "floor", "presets", "generate", "baseline", "loaded", "heap")  # the report's sections, in order
BASELINE = "e800862"  # the commit issue 32 was filed on (2026-12-02): "today's default" of its targets


def _seconds(fn: Callable[[], object]) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def _median_time(fn: Callable[[], object], repeat: int) -> float:
    return statistics.median(_seconds(fn) for _ in range(repeat))


class RenderTiming(NamedTuple):
    seconds: float  # median of the timed renders
    evals: int  # density evaluations of one render
    first_s: float  # the first render (the kernels' build, or Dr.Jit's disk cache), not in the median
    x_floor: float | None  # median over the runs of the render's time over its floor's (None: no floor)
    # the part of x_floor its Dr.Jit kernels ran (their launches' history): the rest is glue, the
    # kernels' Python tracing and torch's ops around them (None: no floor, or no Dr.Jit)
    x_floor_kernels: float | None = None


class Floor(NamedTuple):
    """A render's density-evaluation floor: `kernel` evaluates the density at `points` points."""

    kernel: Callable[[], object]
    points: int
    threads: int


def floor_ratio(render_s: Sequence[float], floor_s: Sequence[float], *, evals: int, points: int) -> float:
    """Median over paired runs of a render's time over the time its `evals` density evaluations take
    at the floor kernel's rate in the run beside it (`points` points in `floor_s`)."""
    return statistics.median(r * points / (evals * f) for r, f in zip(render_s, floor_s, strict=True))


def time_render(scene, *, compile: str | bool, repeat: int, floor: Floor | None = None) -> RenderTiming:
    """`render(scene)` timed `repeat` times after a first call. With a `floor`, its kernel runs after
    each render (on its threads), and × floor is taken run by run: on a VM whose speed drifts, a
    floor measured minutes apart from the render skewed the ratio by up to 2× (docs/SPEED.md); so is
    the part of it that the render's Dr.Jit kernels ran (`kernel_seconds`)."""
    start = time.perf_counter()
    out = render(scene, compile=compile)
    first, render_s, kernel_s, floor_s = time.perf_counter() - start, [], [], []
    for _ in range(repeat):
        seconds, kernels = kernel_seconds(lambda: render(scene, compile=compile))
        render_s.append(seconds)
        kernel_s.append(kernels)
        if floor is not None:
            with torch_threads(floor.threads):
                floor_s.append(_seconds(floor.kernel))
    evals = out.stats["density_evals"]
    ratio = lambda times: floor_ratio(times, floor_s, evals=evals, points=floor.points)  # noqa: E731
    x_floor = ratio(render_s) if floor is not None and evals else None
    x_kernels = ratio(kernel_s) if x_floor is not None and None not in kernel_s else None
    return RenderTiming(statistics.median(render_s), evals, first, x_floor, x_kernels)


def kernel_seconds(fn: Callable[[], object]) -> tuple[float, float | None]:
    """`fn()`'s seconds, and how long the Dr.Jit kernels it launched ran (Dr.Jit's kernel history;
    None where Dr.Jit cannot run)."""
    if not compilation.drjit_available():
        return _seconds(fn), None
    import drjit as dr

    before = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()  # (emptied: only fn's launches below)
    try:
        seconds = _seconds(fn)
        launched = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, before)
    return seconds, sum(k.get("execution_time", 0.0) for k in launched) / 1e3  # (history in ms)


def time_llvmpipe(width: int, height: int, *, repeat: int) -> float | None:
    """Median seconds of the template GLSL on llvmpipe at width×height (None: no EGL/GL context)."""
    from .glsl import gl_context, shadertoy_source, time_fragment

    if gl_context() is None:
        return None
    template = (Path(__file__).parent / "template_clouds.glsl").read_text()
    uniforms = dict(iResolution=(width, height, 1.0), iTime=0.0, iMouse=(0.0, 0.0, 0.0, 0.0))
    return time_fragment(shadertoy_source(template), width, height, uniforms=uniforms,
                         textures={"iChannel0": noise.default_noise_texture(0).numpy()}, repeat=repeat)


def _cloud_puff(width: int, height: int, hash: str) -> dict:
    scene = preset("cloud-puff", width=width, height=height).model_dump()
    scene["volumes"][0]["density"]["fbm"]["hash"] = hash
    return scene


def render_rows(sizes: Sequence[tuple[int, int]], *, repeat: int, physical_size: tuple[int, int],
                floor_points: int = 2**20) -> list[dict]:
    """Rows {work, renderer, threads, seconds, evals_per_s, ratio, x_floor, first_s}: template-clouds
    per size against llvmpipe (by default also on one thread, as a generator's worker renders), then
    cloud-puff at `physical_size` against its table-hash eager render. × floor: against the
    fastest kernel of the render's density on as many threads (`fastest`), run beside each render
    on `floor_points` points."""
    rows, threads = [], torch.get_num_threads()
    kernels = floor_kernels(points=floor_points)

    def floor(density: str, n: int) -> Floor:
        kernel = kernels[(fastest(density), density, n)]
        with torch_threads(n):
            kernel()  # builds: not in the timed runs
        return Floor(kernel, floor_points, n)

    for width, height in sizes:
        gl = time_llvmpipe(width, height, repeat=repeat)
        work = f"template-clouds {width}×{height}"
        if gl is not None:
            rows.append(dict(work=work, renderer="llvmpipe (GLSL template)", threads=None, seconds=gl, evals_per_s=None,
                             ratio=1.0, x_floor=None, first_s=None))
        scene = preset("template-clouds", width=width, height=height)
        default = [("kernels", threads, DEFAULT), ("kernels", 1, f"{DEFAULT}, 1 thread")] if compilation.drjit_available() else []
        for compile, n, name in (("off", threads, "torchvol eager"), *default):
            with torch_threads(n):
                t = time_render(scene, compile=compile, repeat=repeat, floor=floor("template-clouds", n))
            rows.append(dict(work=work, renderer=name, threads=n, seconds=t.seconds, evals_per_s=t.evals / t.seconds,
                             ratio=t.seconds / gl if gl else None, x_floor=t.x_floor, first_s=t.first_s))
    width, height = physical_size
    work, base = f"cloud-puff {width}×{height}", None
    for hash, compile, name in (("table", "off", "table hash, eager"), ("arithmetic", "off", "arithmetic hash, eager"),
                                ("table", "kernels", "table hash, default (Dr.Jit march)"),
                                ("arithmetic", "kernels", "arithmetic hash, default (Dr.Jit march)")):
        t = time_render(_cloud_puff(width, height, hash), compile=compile, repeat=repeat, floor=floor("cloud-puff", threads))
        base = base or t.seconds
        rows.append(dict(work=work, renderer=name, threads=threads, seconds=t.seconds, evals_per_s=t.evals / t.seconds,
                         ratio=t.seconds / base, x_floor=t.x_floor, first_s=t.first_s))
    return rows


def profile_rows(name: str, *, size: int, top: int = 6, hash: str = "table") -> list[dict]:
    """torch.profiler's `top` ops by self CPU time of one eager render of preset `name` at
    size×size (after a warm-up render): rows {op, share, calls}; share of the profiled self CPU time."""
    from torch.profiler import ProfilerActivity, profile

    scene = _cloud_puff(size, size, hash) if name == "cloud-puff" else preset(name, width=size, height=size)
    render(scene, compile="off")
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        render(scene, compile="off")
    events = sorted(prof.key_averages(), key=lambda e: e.self_cpu_time_total, reverse=True)
    total = sum(e.self_cpu_time_total for e in events) or 1.0
    return [dict(op=e.key, share=e.self_cpu_time_total / total, calls=e.count) for e in events[:top]]


DEFAULT = "torchvol default (Dr.Jit march)"  # the template's render as `render` runs it
# each density's floor kernels (`floor_kernels`): eager, and in Dr.Jit where it runs, the fastest
FLOORS = {"cloud-puff": ("arithmetic hash, eager", "arithmetic hash, Dr.Jit kernel"),
          "template-clouds": ("texture noise, 5 octaves (integer filter), eager", "texture noise, 5 octaves, Dr.Jit kernel")}


def fastest(density: str) -> str:
    """The name of `density`'s fastest `floor_kernels` kernel on this machine: Dr.Jit's where it runs."""
    return FLOORS[density][1 if compilation.drjit_available() else 0]


def _in_drjit(fn: Callable, *columns: torch.Tensor) -> Callable[[], object]:
    """`fn` of Dr.Jit copies of `columns` ([N] torch tensors, made once: Float, or Int32 for
    integers) as one Dr.Jit kernel: each call traces, launches on torch's thread count and waits
    for the result."""
    import drjit as dr
    from drjit.llvm import Float, Int32

    args = [Float(c.to(torch.float32).numpy()) if c.is_floating_point() else Int32(c.to(torch.int32).numpy())
            for c in columns]

    def run():
        dr.set_thread_count(torch.get_num_threads())
        out = fn(*args)
        dr.eval(out)
        dr.sync_thread()
        return out

    return run


def floor_kernels(*, points: int, octaves: int = 4) -> dict[tuple[str, str, int], Callable[[], object]]:
    """Each measured render's noise alone on the same `points` random points: cloud-puff's
    `octaves`-octave value-noise fbm (table and arithmetic hash) and the template's 5-octave
    texture-noise fbm (`fields.clouds.cloud_fbm`), eager, and the arithmetic hash's and the
    template's in Dr.Jit where it runs (also on one thread, the floor of the one-thread render
    rows). {(kernel, density (the preset whose floor it is), torch threads): fn}; run each on its
    threads."""
    g = torch.Generator().manual_seed(0)
    p = torch.rand(points, 3, generator=g) * 20.0 - 10.0
    x, y, z = (c.contiguous() for c in p.unbind(1))
    packed = noise.packed_table(noise.texture_table(noise.default_noise_texture(0)))
    base = noise.texture_rows(torch.zeros(points, dtype=torch.long), p.dtype)
    scales = noise.folded_scales(5, dtype=p.dtype, device=p.device)
    n = torch.get_num_threads()
    kernels = {
        ("table hash (noise.fbm over noise.value_noise), eager", "cloud-puff", n):
            lambda: noise.fbm(p, lambda q: noise.value_noise(q, seed=7), octaves=octaves),
        (FLOORS["cloud-puff"][0], "cloud-puff", n): lambda: fastnoise.fbm_value_hashed(p, seed=7, octaves=octaves),
        (FLOORS["template-clouds"][0], "template-clouds", n):
            lambda: cloud_fbm(x, y, z, packed, base, None, octaves=5, scales=scales),
    }
    if not compilation.drjit_available():
        return kernels
    seed, factors = int(fastnoise.mixed_seeds([7], "cpu")[0]), [float(c) for c in scales]
    for k in sorted({n, 1}):
        kernels[(FLOORS["cloud-puff"][1], "cloud-puff", k)] = _in_drjit(
            lambda *q: fastnoise.fbm_sum(fastnoise.hashed(seed), *q, factors, None, octaves, 0.5), x, y, z)
        kernels[(FLOORS["template-clouds"][1], "template-clouds", k)] = _in_drjit(
            lambda *q: cloud_fbm(*q, None, octaves=5, scales=factors), x, y, z, packed, base)
    return kernels


def floor_rows(*, points: int, repeat: int, octaves: int = 4) -> list[dict]:
    """Density evaluations/s of `floor_kernels`, interleaved runs. Rows {kernel, density (the
    preset whose floor it is), threads, evals_per_s, first_s}."""
    kernels = floor_kernels(points=points, octaves=octaves)
    first = {}
    for key, fn in kernels.items():
        with torch_threads(key[2]):
            first[key] = _seconds(fn)
    times: dict = {key: [] for key in kernels}
    for _ in range(repeat):  # interleaved: a change in the machine's load hits every kernel alike
        for key, fn in kernels.items():
            with torch_threads(key[2]):
                times[key].append(_seconds(fn))
    return [dict(kernel=kernel, density=density, threads=threads, evals_per_s=points / statistics.median(t),
                 first_s=first[(kernel, density, threads)]) for (kernel, density, threads), t in times.items()]


def _kernel_floor(out, name: str, kernels: dict, points: int) -> Floor | None:
    """The floor of a render `out` (rendered with `keep_context`) whose every march is a Dr.Jit
    kernel: its densities alone in the Dr.Jit kernel on `points` points, each volume's share of
    them its share of the render's evaluations (`density_lanes.density_kernel` over its bounds'
    box, a layer's heights 20 units across: a slab, a planet's shell; the template's Dr.Jit fbm), None elsewhere."""
    from ..volume import density_lanes

    marches = list(out.stats["plan"]["marches"].values())
    if not marches or any(m != "drjit" for m in marches):
        return None
    n = torch.get_num_threads()
    if name == "template-clouds":
        key = (FLOORS["template-clouds"][1], "template-clouds", n)
        return Floor(kernels[key], points, n) if key in kernels else None
    by_volume, g, parts = out.stats["density_evals_by_volume"], torch.Generator().manual_seed(0), []
    total = sum(by_volume.values())
    for vol in out.context.volumes:
        count = round(points * by_volume.get(vol.plan.name, 0) / total) if total else 0
        if count == 0:
            continue
        b = vol.params.bounds.value
        if vol.bounds.caps["layer"]:  # a slab or a planet's shell (its box the planet's): its heights, 20 units across
            heights = vol.bounds.caps["height_range"](b)[0]
            lo, hi = torch.tensor([[-10.0, float(heights[0]), -10.0]]), torch.tensor([[10.0, float(heights[1]), 10.0]])
        else:
            lo, hi = vol.bounds.caps["aabb"](b)
        parts.append(density_lanes.density_kernel(vol, lo[0] + (hi[0] - lo[0]) * torch.rand(count, 3, generator=g)))
    for kernel in parts:
        kernel()  # builds: not in the timed runs
    return Floor(lambda: [kernel() for kernel in parts], points, n)


def _eager_seconds(scene) -> tuple[float, object, dict]:
    """One eager render of `scene` (`compile="off"`, the reference): (its seconds, its output with
    its context, what its fields evaluated: `renderer.stats.recording_points`' record)."""
    from ..renderer.stats import recording_points

    with recording_points() as record:
        start = time.perf_counter()
        out = render(scene, compile="off", keep_context=True)
        return time.perf_counter() - start, out, record


def _own_points_floor(name: str, eager, record: dict, floor: Floor | None) -> Floor | None:
    """The floor on the render's own points, as issue 32 defines it: each volume's density alone
    in the Dr.Jit kernel at the points (their scenes, the octaves kept) the eager render `eager`
    evaluated (`record`, `_eager_seconds`'), in its order (the kernel render evaluates the same
    points to float rounding), where `floor` (`_kernel_floor`'s, on random points of each volume's
    box) is defined; None elsewhere. A render's points are coherent (neighbouring rays, one step
    at a time) and cost less than random ones: this floor is the lower, its × floor the higher."""
    from ..volume import density_lanes

    if floor is None or name == "template-clouds":  # (its floor: the seed's texture fbm, `FLOORS`)
        return None
    parts, total = [], 0
    for vol in eager.context.volumes:
        calls = record.get(vol.field, [])
        if not calls:
            continue
        points, scenes = torch.cat([c[0] for c in calls]).float(), torch.cat([c[1] for c in calls])
        # a call without LOD keeps every octave: as many as any count can ask for
        kept = None if all(c[2] is None for c in calls) else torch.cat(
            [torch.full_like(c[1], 64) if c[2] is None else c[2] for c in calls])
        parts.append(density_lanes.density_kernel(vol, points, scenes, kept))
        total += points.shape[0]
    for kernel in parts:
        kernel()  # builds: not in the timed runs
    return Floor(lambda: [kernel() for kernel in parts], total, floor.threads) if parts else None


def backends(summary: dict) -> list[str]:
    """What each march of a render ran on (its plan's `summary`): its volumes', then the air's."""
    return list(summary["marches"].values()) + ([summary["air"]] if "air" in summary else [])


def preset_rows(*, size: int, repeat: int, floor_points: int = 2**20) -> list[dict]:
    """Every preset at size×size as `render` runs it by default: rows {preset, marches (what each
    march ran on), seconds, first_s, eager_s (one eager render, where a march ran as a kernel),
    x_floor (against its density alone in the Dr.Jit kernel, where every march is one),
    x_floor_kernels (the part of it its Dr.Jit kernels ran), x_floor_own (against the floor on
    the render's own points, `_own_points_floor`)}."""
    rows, kernels = [], floor_kernels(points=floor_points)
    for name in preset_names():
        scene = preset(name, width=size, height=size)
        out = render(scene, keep_context=True)
        floor = _kernel_floor(out, name, kernels, floor_points)
        t = time_render(scene, compile="kernels", repeat=repeat, floor=floor)
        marches = backends(out.stats["plan"])
        eager, own = None, None
        if "drjit" in marches:  # (the points' copies are ~1% of an eager render)
            eager, eager_out, record = _eager_seconds(scene)
            own = _own_points_floor(name, eager_out, record, floor)
        x_own = None if own is None else time_render(scene, compile="kernels", repeat=repeat, floor=own).x_floor
        rows.append(dict(preset=name, marches=", ".join(sorted(set(marches))) or "none", seconds=t.seconds,
                         first_s=t.first_s, eager_s=eager, x_floor=t.x_floor, x_floor_kernels=t.x_floor_kernels,
                         x_floor_own=x_own))
    return rows


def cli_wall_seconds(path: Path, *, count: int, workers: int, overrides: dict, root: Path = ROOT) -> float:
    """Wall-clock seconds of `torchvol generate` of `count` samples on `workers` workers from a
    fresh process, as a user runs it: the interpreter's start, importing torch, the render and the
    process's exit included. `root`: the checkout whose code runs (another commit's: `baseline`).
    Its sources are byte-compiled first, as `pip install` does: where PYTHONDONTWRITEBYTECODE is
    set (this project's machines), every process would otherwise compile each module it imports
    again (0.3-0.4 s of a fresh `generate` here)."""
    compileall.compile_dir(str(root / "torchvol"), quiet=1)
    sets = [arg for key, value in overrides.items() for arg in ("--set", f"{key}={value}")]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")]))}
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        subprocess.run([sys.executable, "-m", "torchvol.cli", "generate", str(path), "--count", str(count), "--out",
                        str(Path(tmp) / "ds"), "--workers", str(workers), "--no-progress", *sets],
                       check=True, capture_output=True, cwd=root, env=env)
        return time.perf_counter() - start


@contextlib.contextmanager
def checkout(rev: str):
    """A temporary worktree of this repository at commit `rev` (git), removed afterwards: the code
    a baseline row runs."""
    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp) / "tree"
        subprocess.run(["git", "worktree", "add", "--detach", str(tree), rev], check=True, capture_output=True, cwd=ROOT)
        try:
            yield tree
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(tree)], capture_output=True, cwd=ROOT)


def baseline_rows(recipes: Sequence[str], rev: str, *, workers: int = 2, count: int = 64, size: int = 128,
                  repeat: int = 1) -> list[dict]:
    """Each recipe's fresh-CLI wall-clock (`cli_wall_seconds`: `count` samples at size×size on
    `workers` workers, start-up included) by default at commit `rev` and now, in one run, the two
    alternating recipe by recipe, `repeat` times each (their medians: a start-up varies by ±0.3 s
    from process to process, a tenth of a fast recipe's run): rows {recipe, rev, then_s, now_s,
    gain (then / now)}; a recipe `rev` did not have is left out. Issue 32's "every other recipe ≥
    5× today's default" is this gain against the commit the issue was filed on."""
    rows, overrides = [], {"image.width": size, "image.height": size}
    with checkout(rev) as tree:
        for name in recipes:
            if not (tree / "datasets" / f"{name}.toml").exists():
                continue
            runs = [(cli_wall_seconds(tree / "datasets" / f"{name}.toml", count=count, workers=workers,
                                      overrides=overrides, root=tree),
                     cli_wall_seconds(ROOT / "datasets" / f"{name}.toml", count=count, workers=workers, overrides=overrides))
                    for _ in range(repeat)]
            then, now = (statistics.median(r[i] for r in runs) for i in (0, 1))
            rows.append(dict(recipe=name, rev=rev, then_s=then, now_s=now, gain=then / now, count=count, workers=workers))
    return rows


def generation_rows(recipes: Sequence[str], *, workers: Sequence[int], count: int, size: int | None,
                    batch: int | None = None, layout: str = "folder", cli_count: int = 64) -> list[dict]:
    """`generate` of each recipe at size×size (None: the recipe's own size) with each worker count,
    as it runs by default ("kernels": its marches in the Dr.Jit kernels where they have one), and
    eager where that differs:
    rows {recipe, workers, mode, seconds, samples_per_s, steady_per_s, first_s, bytes_per_sample}.
    After a warm-up run (one batch a worker: Dr.Jit's on-disk cache is then warm for both timed
    runs), each is run for N and for 2N samples (N = `count`, 4·`count` in kernels, whose samples
    are fast): the difference is the steady rate (N / (T₂ − T₁)); what the first run took beyond N
    samples at that rate is the start-up (worker processes: `first_s`). `samples_per_s`: 2N / T₂.
    `batch` None: `generate`'s own (`dataset.generate.auto_batch`). The default rows also give
    `cli_wall_s`: `cli_count` samples from a fresh process (`cli_wall_seconds`; None: not run)."""
    from ..dataset.generate import generate
    from ..dataset.recipe import Recipe
    from ..renderer.plan import make_plan

    rows = []
    overrides = {} if size is None else {"image.width": size, "image.height": size}
    for name in recipes:
        path = ROOT / "datasets" / f"{name}.toml"
        scene = Recipe.load(path, overrides).sample_with_params(0, 0)[0]
        kernels = "drjit" in backends(make_plan(scene, compile="kernels").summary())
        modes = [("kernels", "default")] + ([("off", "eager")] if kernels else [])  # without a kernel the default is eager
        for n in workers:
            for compile, label in modes:
                seconds, n_samples = [], count * (4 if compile == "kernels" and kernels else 1)
                for k in (4 * n, n_samples, 2 * n_samples):  # warm-up, N, 2N
                    with tempfile.TemporaryDirectory() as tmp:
                        start = time.perf_counter()
                        generate(path, count=k, out=Path(tmp) / "ds", workers=n, batch=batch, layout=layout,
                                 overrides=overrides, progress=False, compile=compile)
                        seconds.append(time.perf_counter() - start)
                        size_bytes = sum(f.stat().st_size for f in (Path(tmp) / "ds").rglob("*") if f.is_file())
                # the N extra samples must take a measurable share of the 2N run, or the difference is noise
                steady = n_samples / (seconds[2] - seconds[1]) if seconds[2] - seconds[1] > 0.1 * seconds[2] else None
                wall = (cli_wall_seconds(path, count=cli_count, workers=n, overrides=overrides)
                        if cli_count and compile == "kernels" else None)
                rows.append(dict(recipe=name, workers=n, mode=label, samples=2 * n_samples,
                                 seconds=seconds[2], samples_per_s=2 * n_samples / seconds[2], steady_per_s=steady,
                                 first_s=None if steady is None else max(seconds[1] - n_samples / steady, 0.0),
                                 bytes_per_sample=size_bytes / (2 * n_samples), cli_wall_s=wall, cli_count=cli_count))
    return rows


_RENDER_CHILD = textwrap.dedent("""
    import json, resource, statistics, sys, time
    import torchvol as tv
    tv.tune_process()  # before torch loads: its OpenMP wait policy and heap settings, as `torchvol` commands get them
    import torch
    threads, name, width, height, repeat, compile = sys.argv[1:]
    torch.set_num_threads(int(threads))
    scene = tv.preset(name, width=int(width), height=int(height))
    tv.render(scene, compile=compile)
    times, faults, system = [], [], []
    for _ in range(int(repeat)):
        before, start = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        tv.render(scene, compile=compile)
        after = resource.getrusage(resource.RUSAGE_SELF)
        times.append(time.perf_counter() - start)
        faults.append(after.ru_minflt - before.ru_minflt)
        system.append(after.ru_stime - before.ru_stime)
    print(json.dumps(dict(seconds=statistics.median(times), faults=statistics.median(faults),
                          system_s=statistics.median(system))))
""")


def _child_render(threads: int, width: int, height: int, repeat: int, *, name: str = "template-clouds",
                  compile: str = "off", env: dict[str, str] | None = None) -> dict:
    """Preset `name` rendered in a fresh process (after one render) -> medians over `repeat` renders
    {seconds, faults (minor page faults), system_s (system CPU seconds)}; `env` added to ours."""
    env = {**os.environ, **(env or {}),
           "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    env.pop("OMP_NUM_THREADS", None)  # the child sets its own thread count
    out = subprocess.run([sys.executable, "-c", _RENDER_CHILD, str(threads), name, str(width), str(height), str(repeat),
                          compile], env=env, check=True, capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def loaded_rows(*, width: int, height: int, repeat: int,
                configs: Sequence[tuple[int, str, str]] | None = None) -> list[dict]:
    """template-clouds at width×height in a fresh process, alone and with one busy competitor, per
    (torch threads, OMP_WAIT_POLICY, compile mode): rows {threads, policy, compile, alone_s,
    loaded_s, slowdown}. In kernels, the march is Dr.Jit's kernel where it runs, on its own threads."""
    cores = os.cpu_count() or 1
    configs = configs or [(cores, "ACTIVE", "off"), (cores, "PASSIVE", "off"), (max(1, cores - 1), "PASSIVE", "off"),
                          (cores, "PASSIVE", "kernels")]
    rows = []
    for threads, policy, compile in configs:
        policy_env = {"OMP_WAIT_POLICY": policy}
        alone = _child_render(threads, width, height, repeat, compile=compile, env=policy_env)["seconds"]
        busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
        try:
            loaded = _child_render(threads, width, height, repeat, compile=compile, env=policy_env)["seconds"]
        finally:
            busy.kill()
            busy.wait()
        rows.append(dict(threads=threads, policy=policy, compile=compile, alone_s=alone, loaded_s=loaded,
                         slowdown=loaded / alone))
    return rows


def heap_rows(works: Sequence[tuple[str, int, int, str, int]], *, repeat: int) -> list[dict]:
    """Each (preset, width, height, compile mode, torch threads) in fresh processes, glibc's heap as
    torchvol sets it (`torchvol.runtime.heap`) and left alone (TORCHVOL_HEAP=system), alternately: rows
    {work, compile, threads, heap, seconds, faults, system_s}."""
    rows = []
    for name, width, height, compile, threads in works:
        for heap, env in (("glibc's defaults", {"TORCHVOL_HEAP": "system"}), ("torchvol", {"TORCHVOL_HEAP": "torchvol"})):
            run = _child_render(threads, width, height, repeat, name=name, compile=compile, env=env)
            rows.append(dict(work=f"{name} {width}×{height}", compile=compile, threads=threads, heap=heap, **run))
    return rows


def _fmt(value, spec: str = ".3f") -> str:
    return "" if value is None else format(value, spec)


def markdown(sections: dict) -> str:
    """The report: machine line, then each measured section as a Markdown table."""
    lines = _header(sections)
    for name, section in _SECTIONS.items():
        if name in sections:
            lines += section(sections)
    return "\n".join(lines)


def _header(sections: dict) -> list[str]:
    """The report's title and machine line: how it was run, on what, with what."""
    from .glsl import renderer_name

    count_flag = f" --count {sections['count']}" if sections.get("count", 16) != 16 else ""
    if sections.get("recipes"):
        count_flag = f" --recipes {' '.join(sections['recipes'])}" + count_flag
    lines = ["# Speed", "", (f"`torchvol bench speed{' --quick' if sections['quick'] else ''}{count_flag}`, {time.strftime('%Y-%m-%d')}: "
             f"torch {torch.__version__}, {torch.get_num_threads()} torch threads, {os.cpu_count()} CPUs, "
             f"{platform.processor() or platform.machine()}; GL: {renderer_name()}. Medians of {sections['repeat']} runs; "
             "a kernel's build (first call) reported apart. Ratios hold on a busy machine; absolute times only on a quiet "
             "one. `torchvol bench speed --out docs/SPEED.md` writes this page (`--quick`: small sizes, two recipes)."), ""]
    return lines


def _profile_section(sections: dict) -> list[str]:
    """The report's section on where the time goes (torch.profiler's top ops, one render each):
    its Markdown lines."""
    lines = ["## Where the time goes (torch.profiler, self CPU time, one render)", "",
             "| render | op | share | calls |", "| --- | --- | ---: | ---: |"]
    lines += [f"| {name} | `{r['op']}` | {r['share']:.0%} | {r['calls']} |" for name, rows in sections["profile"].items() for r in rows]
    lines += ["", "Gathers (the value noise's permutation chain perm[perm[perm[x] + y] + z], 14 per point and "
              "octave; the march's and the DDA's compaction) run as `aten::index_select` (`mathops.take_rows`, 3–5× "
              "faster than `x[ids]`'s `aten::index`); `density.fbm.hash = \"arithmetic\"` replaces the permutation "
              "with integer arithmetic (torchvol.noise.fast). These are eager renders (`compile=\"off\"`, the "
              "reference): by default the march is one Dr.Jit kernel, which torch.profiler does not see into.", ""]
    return lines


def _render_section(sections: dict) -> list[str]:
    """The report's section on the renders' times, ratios and floors: its Markdown lines."""
    lines = ["## Renders", "", "| work | renderer | median s | density evals/s | ratio | × floor | first call s |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: |"]
    lines += [f"| {r['work']} | {r['renderer']} | {r['seconds']:.3f} | {_fmt(r['evals_per_s'], ',.0f')} | "
              f"{_fmt(r['ratio'], '.2f')} | {_fmt(r['x_floor'], '.2f')} | {_fmt(r['first_s'], '.1f')} |"
              for r in sections["render"]]
    lines += ["", "× floor: the render's time over its density-evaluation floor, the time its density evaluations alone "
              "take in the fastest kernel for that density on as many threads (next table), that kernel run after each "
              "render and the ratio taken run by run (the median of the runs' ratios): 1 would be a render that "
              "costs nothing but its noise. "
              "Ratio: time over llvmpipe's (template-clouds) or over the table-hash eager render (cloud-puff). "
              "By default (`compile=\"kernels\"`) template-clouds runs its march as one Dr.Jit kernel per chunk where "
              "Dr.Jit's LLVM backend runs (torchvol/volume/kernel_march.py, `march_look`: a loop per ray, the light's "
              "fbm under a per-sample branch, one launch), and cloud-puff its physical march (`march`). The floor is "
              "the Dr.Jit fbm, the fastest. \"1 thread\": as a generator's worker renders (one torch thread each, "
              "workers scale by processes): the render's eager glue (rays, compositing, post: small ops) runs on one "
              "thread, where waking a second costs more than it saves, so a second thread speeds the kernels only "
              "(docs/VOLUMES.md, \"Two threads\"). Density evals/s count the evaluations the eager march makes, "
              "which the kernel makes too.", ""]
    return lines


def _floor_section(sections: dict) -> list[str]:
    """The report's section on each render's density noise alone: its Markdown lines."""
    lines = ["## The floor: each render's noise alone", "", "| density of | kernel | threads | evals/s | first call s |",
             "| --- | --- | ---: | ---: | ---: |"]
    lines += [f"| {r['density']} | {r['kernel']} | {r['threads']} | {r['evals_per_s']:,.0f} | {r['first_s']:.1f} |"
              for r in sections["floor"]]
    lines += [""]
    return lines


def _presets_section(sections: dict) -> list[str]:
    """The report's section on every preset's default render: its Markdown lines."""
    size = sections["preset_size"]
    lines = [f"## Presets: the default render, {size}×{size}", "",
             "| preset | marches on | default s | eager s | × eager | × floor | of it, kernels | × floor, own points | first call s |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    lines += [f"| {r['preset']} | {r['marches']} | {r['seconds']:.3f} | {_fmt(r['eager_s'])} | "
              f"{_fmt(None if r['eager_s'] is None else r['eager_s'] / r['seconds'], '.1f')} | {_fmt(r['x_floor'], '.2f')} | "
              f"{_fmt(r.get('x_floor_kernels'), '.2f')} | {_fmt(r.get('x_floor_own'), '.2f')} | {_fmt(r['first_s'], '.2f')} |"
              for r in sections["presets"]]
    lines += ["", "What `render(scene)` does without flags (`compile=\"kernels\"`): a march whose technique has a Dr.Jit "
              "kernel runs in it (\"drjit\": torchvol/volume/kernel_march.py, the physical media and the seeds' "
              "looks), the others eagerly; `stats[\"plan\"][\"marches\"]` "
              "says which. × eager: one eager render (`compile=\"off\"`, the reference) over the default's median. × floor: "
              "the render's time over the time its density evaluations alone take in the Dr.Jit kernel (the same "
              "density function, traced alone, on random points of its bounds' box), run beside each render; only "
              "where every march is a kernel. Of it, kernels: the part of × floor the render's Dr.Jit kernels ran "
              "(Dr.Jit's kernel history); the rest is glue, the kernels' Python tracing and torch's ops around them. × floor, own "
              "points: against the same density kernel at the very points (scenes, octaves kept) the render evaluates, "
              "recorded from its eager reference in its order (issue 32's definition): coherent points, cheaper than "
              "random ones, so the higher ratio. "
              "First call: the first render in this process, the kernel's build "
              "(or Dr.Jit's disk cache) included.", ""]
    return lines


def _generate_section(sections: dict) -> list[str]:
    """The report's section on the generator's throughput: its Markdown lines."""
    cli = next((r["cli_count"] for r in sections["generate"] if r.get("cli_wall_s") is not None), 64)
    lines = ["## Generation", "", "| recipe | workers | mode | samples | seconds | samples/s | steady samples/s | start-up s | "
             f"bytes/sample | fresh CLI, {cli} samples: wall s | its samples/s |",
             "| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    lines += [f"| {r['recipe']} | {r['workers']} | {r['mode']} | {r['samples']} | {r['seconds']:.2f} | {r['samples_per_s']:.2f} | "
              f"{_fmt(r['steady_per_s'], '.2f')} | {_fmt(r['first_s'], '.1f')} | {r['bytes_per_sample']:,.0f} | "
              f"{_fmt(r.get('cli_wall_s'), '.2f')} | {_fmt(None if r.get('cli_wall_s') is None else r['cli_count'] / r['cli_wall_s'], '.1f')} |"
              for r in sections["generate"]]
    lines += ["", f"Each row generates one batch a worker (warm-up), then N = {sections.get('count', 16)} and 2N samples "
              "(N four times as many in kernels; samples, seconds and samples/s are the 2N run's): steady samples/s = "
              "N / (T₂ − T₁), start-up = what the N run took beyond N samples at that rate (worker processes; blank "
              "where the N extra samples took under a tenth of the 2N run: the difference is then noise, not a rate). "
              "default: `torchvol generate` without flags (a march whose technique has a Dr.Jit kernel runs in it); "
              "eager: `--eager`, where that differs. Worker processes are forked (one thread each): their start-up is "
              "the fork's, not an import of torch. Fresh CLI: `python -m torchvol.cli generate` of that many samples "
              "from a new process, timed from outside (the interpreter's start, importing torch, the workers, the "
              "render and the exit: what a user waits for).", ""]
    return lines


def _baseline_section(sections: dict) -> list[str]:
    """The report's section on each recipe against a past commit's default: its Markdown lines."""
    rows = sections["baseline"]
    lines = [f"## Against `{rows[0]['rev']}`'s default" if rows else "## Against a past commit's default", "",
             "| recipe | then: wall s | now: wall s | gain |", "| --- | ---: | ---: | ---: |"]
    lines += [f"| {r['recipe']} | {r['then_s']:.2f} | {r['now_s']:.2f} | {r['gain']:.1f}× |" for r in rows]
    if rows:
        lines += ["", f"`torchvol generate` without flags from a fresh process, {rows[0]['count']} samples at 128² on "
                  f"{rows[0]['workers']} workers, timed from outside (start-up included): the commit's code in a git "
                  "worktree (its own recipe of that name) and this checkout's, alternating recipe by recipe in one run "
                  f"(medians of {sections['repeat'] if not sections['quick'] else 1} runs each), each checkout's sources "
                  "byte-compiled first as `pip install` compiles them. "
                  f"`{BASELINE}` (the default `--baseline`): the commit issue 32 was filed on, whose default was eager.", ""]
    return lines


def _loaded_section(sections: dict) -> list[str]:
    """The report's section on renders alone and beside one busy competitor: its Markdown lines."""
    lines = ["## One busy competitor", "", "template-clouds in a fresh process, alone and while `python -c \"while True: "
             "pass\"` keeps a core busy. torchvol's processes set OMP_WAIT_POLICY=PASSIVE unless the environment says otherwise "
             "(`tv.tune_process()`): spinning OpenMP threads fight the competitor at every one of a render's small ops.", "", "| torch threads | OMP_WAIT_POLICY | compile | alone s | loaded s | slowdown |",
             "| ---: | --- | --- | ---: | ---: | ---: |"]
    lines += [f"| {r['threads']} | {r['policy']} | {r['compile']} | {r['alone_s']:.3f} | {r['loaded_s']:.3f} | "
              f"{r['slowdown']:.2f} |"
              for r in sections["loaded"]]
    lines += ["", "Where waking a sleeping thread is slow (some VMs), two PASSIVE threads are slower alone than "
              "loaded and than one thread; one thread is the setting that is never far off, alone or loaded, so the "
              "generator runs one a worker and scales by processes (docs/DATASETS.md, \"Threads on a shared machine\").", ""]
    return lines


def _heap_section(sections: dict) -> list[str]:
    """The report's section on renders with glibc's heap as torchvol sets it and left alone: its
    Markdown lines."""
    lines = ["## The heap", "", ("Renders in fresh processes with glibc's malloc left alone (`TORCHVOL_HEAP=system`) "
             "and as `tv.tune_process()` sets it (torchvol/runtime/heap.py: freed blocks up to 32 MiB stay in the heap, whose "
             "top is handed back past 64 MiB). Page faults and system CPU seconds per render."), "",
             "| work | compile | threads | heap | median s | page faults | system s |",
             "| --- | --- | ---: | --- | ---: | ---: | ---: |"]
    lines += [f"| {r['work']} | {r['compile']} | {r['threads']} | {r['heap']} | {r['seconds']:.3f} | {r['faults']:,.0f} | "
              f"{r['system_s']:.3f} |" for r in sections["heap"]]
    lines += ["", ("A march step allocates and frees a wavefront's tensors (a few MB) at every step; glibc's defaults "
                   "serve them from fresh mappings or hand the heap's top back, and every page of the next step's "
                   "tensors is faulted in and zeroed by the kernel again: on two threads both wait on it. glibc's default "
                   "thresholds move with the largest mapped block a process has freed, so with them whether the heap "
                   "is handed back varies from process to process, even for one script (12 of 30 fresh processes "
                   "running tests/test_heap.py's rounds kept their tensors); torchvol's fixed thresholds keep it every time."), ""]
    return lines


# the report's sections, in their order on the page
_SECTIONS = {"profile": _profile_section, "render": _render_section, "floor": _floor_section,
             "presets": _presets_section, "generate": _generate_section, "baseline": _baseline_section,
             "loaded": _loaded_section, "heap": _heap_section}


def speed(out: str | Path | None = None, *, quick: bool = False, repeat: int | None = None,
          recipes: Sequence[str] | None = None, count: int | None = None,
          parts: Sequence[str] = PARTS, baseline: str = BASELINE) -> str:
    """Run the benchmark; returns the Markdown (and writes it to `out` where given). `quick`: small
    sizes, two recipes, fewer points (about 2 minutes on 2 cores). `baseline`: the commit whose default
    generation the "baseline" part times each recipe against (`baseline_rows`)."""
    repeat = repeat or (2 if quick else 3)
    sections: dict = {"quick": quick, "repeat": repeat}
    if "profile" in parts:
        size = 32 if quick else 64
        sections["profile"] = {f"{name} {size}×{size}": profile_rows(name, size=size) for name in ("cloud-puff", "template-clouds")}
    if "render" in parts:
        sizes = ((160, 90),) if quick else TEMPLATE_SIZES
        sections["render"] = render_rows(sizes, repeat=repeat, physical_size=(48, 48) if quick else (128, 128),
                                         floor_points=2**16 if quick else 2**20)
    if "floor" in parts:
        sections["floor"] = floor_rows(points=2**16 if quick else 2**20, repeat=repeat)
    if "presets" in parts:
        sections["preset_size"] = 48 if quick else 256
        sections["presets"] = preset_rows(size=sections["preset_size"], repeat=repeat,
                                          floor_points=2**16 if quick else 2**20)
    if "generate" in parts:
        chosen = recipes or (("clouds", "template-clouds") if quick else RECIPES)
        sections["recipes"] = list(recipes) if recipes else None
        sections["count"] = count or (4 if quick else 16)
        sections["generate"] = generation_rows(chosen, workers=(1, 2), count=sections["count"], size=32 if quick else 128)
    if "baseline" in parts:
        chosen = recipes or (("clouds", "template-clouds") if quick else RECIPES)
        sections["baseline"] = baseline_rows(chosen, baseline, count=16 if quick else 64, size=32 if quick else 128,
                                             repeat=1 if quick else repeat)
    if "loaded" in parts:
        # quick: a small render (2 threads spinning against a competitor run ~20x longer), 3 runs: the ratio is noisy
        sections["loaded"] = loaded_rows(width=64 if quick else 320, height=36 if quick else 180, repeat=3 if quick else repeat)
    if "heap" in parts:
        cores = os.cpu_count() or 1
        works = ([("template-clouds", 64, 36, "kernels", cores)] if quick else
                 [("template-clouds", 640, 360, "kernels", cores), ("template-clouds", 640, 360, "kernels", 1),
                  ("voxel-gi", 128, 128, "kernels", 1)])
        sections["heap"] = heap_rows(works, repeat=repeat)
    text = markdown(sections)
    if out is not None:
        Path(out).write_text(text + "\n")
    return text
