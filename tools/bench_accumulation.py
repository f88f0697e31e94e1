"""Progressive accumulation at equal time: N passes of k steps (`image.passes = N`, each pass with
its own hashed march dither) against one pass of N·k steps, on cloud-puff, both measured against a
reference from `torchvol.measure.reference.Ladder` (the error-controlled march, with its bound).

    python tools/bench_accumulation.py [--size 128] [--steps 4,8,16] [--passes 1,4,16] [--repeat 1]
                                       [--cache DIR] [--threads 1]

Prints a Markdown table: per (k, N) the image RMSE, median render time and density evaluations
(the machine-independent cost) of the accumulated passes (running mean, and the seeds' exponential
blend with weight 0.05) and of the single N·k-step pass. One warm-up render is not timed.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

import torchvol as tv
from torchvol.measure.reference import Ladder, image_error
from torchvol.scene.presets import preset_dict


def timed(data: dict, overrides: dict, repeat: int):
    """(median seconds, last output) of `repeat` renders of `data` with `overrides`; the output's
    stats carry its density evaluations."""
    scene = tv.load_scene(data, overrides)
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        out = tv.render(scene, seed=0)
        times.append(time.perf_counter() - start)
    return statistics.median(times), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--steps", default="4,8,16", help="steps per pass k")
    ap.add_argument("--passes", default="1,4,16", help="passes N")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/torchvol-bench-accumulation"))
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    data = preset_dict("cloud-puff", width=args.size, height=args.size)
    steps, passes = [int(x) for x in args.steps.split(",")], [int(x) for x in args.passes.split(",")]
    tv.render(tv.load_scene(data), seed=0)  # warm-up: lazy tables and allocations are not what is timed
    rows = []
    for k in steps:
        for n in passes:
            row = {"k": k, "N": n}
            row["mean_s"], out = timed(data, {"march.steps": k, "image.passes": n}, args.repeat)
            row["mean_image"], row["changes"], row["mean_evals"] = out.image, out.stats.get("accumulation", []), out.stats["density_evals"]
            if n > 1:
                row["exp_s"], out = timed(data, {"march.steps": k, "image.passes": n, "image.blend": "exponential"},
                                          args.repeat)
                row["exp_image"] = out.image
                row["one_s"], out = timed(data, {"march.steps": n * k}, args.repeat)
                row["one_image"], row["one_evals"] = out.image, out.stats["density_evals"]
            rows.append(row)
    ladder = Ladder(data, seed=0, spp=1, cache=args.cache)
    images = [r[key] for r in rows for key in ("mean_image", "one_image") if key in r]
    ref = ladder.settle(images, factor=3.0)
    print(f"cloud-puff {args.size}x{args.size}, {args.threads} thread(s); reference: rung {ref.rung} "
          f"(tolerance {ref.tolerance:g}, {ref.dtype}), its RMSE bound {ref.bound:.2e}\n")
    print("| k steps | N passes | N×k mean: RMSE | time s | density evals | N×k exponential 0.05: RMSE | time s "
          "| 1×(N·k): RMSE | time s | density evals | last mean abs change |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        def err(key: str, r: dict = r) -> float:
            return image_error(r[key], ref.image)["rmse"]

        exp = f"{err('exp_image'):.2e} | {r['exp_s']:.2f}" if "exp_image" in r else "– | –"
        one = f"{err('one_image'):.2e} | {r['one_s']:.2f} | {r['one_evals']:.3g}" if "one_image" in r else "(same) | – | –"
        last = f"{r['changes'][-1]:.1e}" if r["changes"] else "–"
        print(f"| {r['k']} | {r['N']} | {err('mean_image'):.2e} | {r['mean_s']:.2f} | {r['mean_evals']:.3g} | {exp} | {one} | {last} |")


if __name__ == "__main__":
    main()
