"""Renders COUNT random scenes over every volumetric technique (`torchvol.measure.fuzz`) and
reports each that gives a NaN, an Inf, an exception other than a ValueError naming a key, or an
output out of range; the failing scenes are written as JSON to OUT.

    python tools/fuzz.py --count 1000 --seed 0 --out fuzz-failures
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from tqdm import tqdm

from torchvol.measure.fuzz import fuzz


def main() -> None:
    """Runs the fuzz and prints its summary."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("fuzz-failures"))
    args = parser.parse_args()
    start = time.perf_counter()
    with tqdm(total=args.count, desc="scenes") as bar:
        failures, refused = fuzz(args.count, seed=args.seed, first=args.first, progress=bar.update)
    elapsed = time.perf_counter() - start
    if failures:
        args.out.mkdir(parents=True, exist_ok=True)
    for f in failures:
        (args.out / f"{f.index}.json").write_text(json.dumps({"error": f.error, "scene": f.scene}, indent=1, default=str))
        print(f"scene {f.index}: {f.error.strip().splitlines()[-1]}")
    print(f"{args.count} scenes (seed {args.seed}): {len(failures)} failures, {refused} refused naming the key,"
          f" {elapsed:.0f} s")


if __name__ == "__main__":
    main()
