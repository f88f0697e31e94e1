"""Generation throughput and output size: samples/s and bytes per sample of each bundled recipe at
its default size, 1 and 2 workers (`torchvol.measure.bench_speed.generation_rows`; `torchvol bench speed`
runs it at 128×128).

    python tools/bench_generate.py [--count 8] [--batch B] [--workers 1 2] [--layout folder]

Each run writes a fresh dataset (the full `torchvol generate` path: sampling, batched render,
PNG/npy/npz encoding, atomic writes, manifest). Worker runs include process start-up. Bytes per
sample: every file of the dataset (meta.json and manifest.jsonl included) over the sample count.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torchvol.measure.bench_speed import RECIPES, generation_rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=8)
    parser.add_argument("--batch", type=int, default=None, help="samples a batch (default: generate's own)")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--recipes", nargs="+", default=RECIPES)
    parser.add_argument("--layout", choices=["folder", "webdataset"], default="folder")
    args = parser.parse_args()
    print(f"cores: {os.cpu_count()}  count: {args.count}  batch: {args.batch}  layout: {args.layout}")
    print(f"{'recipe':<18} {'workers':>7} {'mode':>8} {'samples':>7} {'seconds':>8} {'samples/s':>10} {'steady/s':>9} "
          f"{'bytes/sample':>13}")
    for name in args.recipes:
        for r in generation_rows([name], workers=args.workers, count=args.count, size=None, batch=args.batch, layout=args.layout,
                                 cli_count=0):
            steady = "" if r["steady_per_s"] is None else f"{r['steady_per_s']:.2f}"
            print(f"{name:<18} {r['workers']:>7} {r['mode']:>8} {r['samples']:>7} {r['seconds']:>8.2f} {r['samples_per_s']:>10.3f} "
                  f"{steady:>9} {r['bytes_per_sample']:>13,.0f}", flush=True)


if __name__ == "__main__":
    main()
