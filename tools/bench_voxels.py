"""Benchmark: voxel traversal throughput — the voxel-carved-box preset and a size³ terrain
(voxel-terrain preset, default 256 cells per side) at 640×360, plain DDA vs hybrid traversal,
eager (`compile="off"`) vs the default, the walk one Dr.Jit kernel (docs/VOXELS.md), the same bits.

    python tools/bench_voxels.py [--size 256] [--width 640 --height 360] [--repeat 2] [--threads N]
                                 [--eager-only]

Prints a Markdown table: median wall time of `repeat` renders (after one warm-up render, which
also builds the kernels), rays/s and primary DDA steps/s (stats["voxel_steps"]; hybrid counts its
distance-field jumps as steps), and the share of time in the voxels.dda pass.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

import torchvol as tv


def bench(scene, *, compile: str, repeat: int):
    tv.render(scene, compile=compile)  # warm-up (and the kernels' build)
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = tv.render(scene, compile=compile)
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=360)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--eager-only", action="store_true")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, {args.width}x{args.height}\n")
    print("| scene | traversal | mode | time s | rays/s | DDA steps | steps/s | dda share |")
    print("| --- | --- | --- | ---: | ---: | ---: | ---: | ---: |")
    scenes = [("carved box", lambda tr: tv.load_scene(tv.preset("voxel-carved-box", width=args.width, height=args.height),
                                                      overrides={"voxels.traversal": tr})),
              (f"terrain {args.size}³", lambda tr: tv.preset("voxel-terrain", width=args.width, height=args.height,
                                                             size=args.size, traversal=tr))]
    modes = ["off"] + ([] if args.eager_only else ["kernels"])
    for name, make in scenes:
        for traversal in ("dda", "hybrid"):
            scene = make(traversal)
            for mode in modes:
                secs, out = bench(scene, compile=mode, repeat=args.repeat)
                rays, steps = out.stats["rays"], out.stats["voxel_steps"]
                share = out.stats["time_s"].get("voxels.dda", 0.0) / max(out.stats["total_s"], 1e-12)
                print(f"| {name} | {traversal} | {'eager' if mode == 'off' else 'kernel'} | {secs:.3f} | {rays / secs:,.0f} | "
                      f"{steps:,} | {steps / secs:,.0f} | {share:.0%} |", flush=True)


if __name__ == "__main__":
    main()
