"""Generation throughput and output size: samples/s and bytes per sample of each bundled recipe at
its default size, 1 and 2 workers.

    python tools/bench_generate.py [--count 8] [--batch 4] [--workers 1 2] [--layout folder]

Each run writes a fresh dataset (the full `torchvol generate` path: sampling, batched render,
PNG/npy/npz encoding, atomic writes, manifest). Worker runs include process start-up. Bytes per
sample: every file of the dataset (meta.json and manifest.jsonl included) over the sample count.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchvol.generate import generate  # noqa: E402

BUNDLED = sorted(p.stem for p in (ROOT / "datasets").glob("*.toml"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=8)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--recipes", nargs="+", default=BUNDLED)
    parser.add_argument("--layout", choices=["folder", "webdataset"], default="folder")
    args = parser.parse_args()
    print(f"cores: {os.cpu_count()}  count: {args.count}  batch: {args.batch}  layout: {args.layout}")
    print(f"{'recipe':<18} {'workers':>7} {'seconds':>8} {'samples/s':>10} {'bytes/sample':>13}")
    for name in args.recipes:
        for workers in args.workers:
            with tempfile.TemporaryDirectory() as tmp:
                start = time.perf_counter()
                generate(ROOT / "datasets" / f"{name}.toml", count=args.count, out=Path(tmp) / "ds",
                         workers=workers, batch=args.batch, layout=args.layout, progress=False)
                seconds = time.perf_counter() - start
                size = sum(p.stat().st_size for p in (Path(tmp) / "ds").rglob("*") if p.is_file())
            print(f"{name:<18} {workers:>7} {seconds:>8.2f} {args.count / seconds:>10.3f} {size / args.count:>13,.0f}", flush=True)


if __name__ == "__main__":
    main()
