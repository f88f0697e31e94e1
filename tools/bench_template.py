"""Benchmark: the template-clouds preset in torchvol (eager, and by default: its march one Dr.Jit
kernel) against the same GLSL template on Mesa llvmpipe, at 640×360 and 1280×720.

    python tools/bench_template.py [--repeat 3] [--sizes 640x360,1280x720] [--threads N]

Prints a Markdown table: median wall time of `repeat` renders (after one warm-up render, which also
builds the kernel or loads it from Dr.Jit's cache), density evaluations per second, and the ratio to llvmpipe
measured in the same run. llvmpipe uses all CPU threads it finds (LP_NUM_THREADS to change).
`torchvol bench speed` runs the same comparison (torchvol.measure.bench_speed) with the rest of docs/SPEED.md.
"""

from __future__ import annotations

import argparse
import os
import platform

import torch

from torchvol.measure.bench_speed import time_llvmpipe, time_render
from torchvol.measure.glsl import renderer_name
from torchvol.scene.model import preset


def time_torchvol(width: int, height: int, *, compile: str, repeat: int) -> tuple[float, int]:
    timing = time_render(preset("template-clouds", width=width, height=height), compile=compile, repeat=repeat)
    return timing.seconds, timing.evals


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
        for compile in ("off", "kernels"):
            seconds, evals = time_torchvol(width, height, compile=compile, repeat=args.repeat)
            ratio = f"{seconds / gl:.1f}" if gl else "n/a"
            name = "torchvol, the Dr.Jit march" if compile == "kernels" else "torchvol, eager"
            print(f"| {size} | {name} | {seconds:.3f} | {evals / seconds:,.0f} | {ratio} |", flush=True)


if __name__ == "__main__":
    main()
