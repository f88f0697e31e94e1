"""What a batch's size costs a sample: CPU milliseconds a sample of each recipe rendered in batches
of 1, 4, 8, 16 and 32 samples (`dataset.datasets.render_samples`, one torch thread, one process;
the median of `--repeat` runs over `--count` samples after a warm-up batch). `generate`'s default
batch (`dataset.generate.auto_batch`) comes from these figures (docs/SPEED.md, "Batch size").

    python tools/bench_batch.py [--recipes clouds voxel-terrain] [--count 32] [--repeat 3]

CPU time (`time.process_time`, Dr.Jit's pool included) rather than wall-clock: the figures hold on a
machine that is not quiet, though a busy neighbour still slows them through the shared caches.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchvol.dataset.datasets import render_samples
from torchvol.dataset.recipe import Recipe


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--recipes", nargs="+", default=["clouds", "voxel-terrain"])
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 4, 8, 16, 32])
    parser.add_argument("--count", type=int, default=32)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    print("| recipe | rays a sample | " + " | ".join(f"batch {b}" for b in args.batches) + " |")
    print("| --- | ---: | " + " | ".join("---:" for _ in args.batches) + " |")
    for name in args.recipes:
        recipe = Recipe.load(ROOT / "datasets" / f"{name}.toml")
        image = recipe.sample_with_params(0, 0)[0].image
        render_samples(recipe, list(range(max(args.batches))))  # warm-up: the kernels built or loaded
        cells = []
        for b in args.batches:
            runs = []
            for _ in range(args.repeat):
                start = time.process_time()
                for first in range(1000, 1000 + args.count, b):
                    render_samples(recipe, list(range(first, min(first + b, 1000 + args.count))))
                runs.append((time.process_time() - start) / args.count * 1000)
            cells.append(f"{statistics.median(runs):.1f} ms")
        print(f"| {name} | {image.width * image.height * recipe.views:,} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
