"""Benchmark: the template-clouds preset in torchvol (eager, torch.compile) against the same GLSL
template on Mesa llvmpipe, at 640×360 and 1280×720.

    python tools/bench_template.py [--repeat 3] [--sizes 640x360,1280x720] [--threads N]

Prints a Markdown table: median wall time of `repeat` renders (after one warm-up render, which also
pays torch.compile's compilation), density evaluations per second, and the ratio to llvmpipe
measured in the same run. llvmpipe uses all CPU threads it finds (LP_NUM_THREADS to change).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import torch

import torchvol as tv
from torchvol import noise
from torchvol.testing.glsl import gl_context, renderer_name, shadertoy_source, time_fragment

TEMPLATE = (Path(tv.__file__).parent / "testing" / "template_clouds.glsl").read_text()


def time_torchvol(width: int, height: int, *, compile: bool, repeat: int) -> tuple[float, int]:
    scene = tv.preset("template-clouds", width=width, height=height)
    tv.render(scene, compile=compile)  # warm-up (and compilation)
    times, evals = [], 0
    for _ in range(repeat):
        start = time.perf_counter()
        out = tv.render(scene, compile=compile)
        times.append(time.perf_counter() - start)
        evals = out.stats["density_evals"]
    return statistics.median(times), evals


def time_llvmpipe(width: int, height: int, *, repeat: int) -> float | None:
    if gl_context() is None:
        return None
    uniforms = dict(iResolution=(width, height, 1.0), iTime=0.0, iMouse=(0.0, 0.0, 0.0, 0.0))
    texture = noise.default_noise_texture(0).numpy()
    return time_fragment(shadertoy_source(TEMPLATE), width, height, uniforms=uniforms,
                         textures={"iChannel0": texture}, repeat=repeat)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--sizes", default="640x360,1280x720")
    parser.add_argument("--threads", type=int, default=None, help="torch.set_num_threads")
    args = parser.parse_args()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, {os.cpu_count()} CPUs, "
          f"{platform.processor() or platform.machine()}; GL: {renderer_name()}\n")
    print("| size | renderer | median time (s) | density evals/s | time / llvmpipe |")
    print("| --- | --- | ---: | ---: | ---: |")
    for size in args.sizes.split(","):
        width, height = (int(v) for v in size.split("x"))
        gl = time_llvmpipe(width, height, repeat=args.repeat)
        if gl is not None:
            print(f"| {size} | llvmpipe (GLSL template) | {gl:.3f} | | 1.0 |")
        for compile in (False, True):
            seconds, evals = time_torchvol(width, height, compile=compile, repeat=args.repeat)
            ratio = f"{seconds / gl:.1f}" if gl else "n/a"
            name = "torchvol, torch.compile" if compile else "torchvol, eager"
            print(f"| {size} | {name} | {seconds:.3f} | {evals / seconds:,.0f} | {ratio} |", flush=True)


if __name__ == "__main__":
    main()
