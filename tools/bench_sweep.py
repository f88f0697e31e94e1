"""Wall time of the README's sweep example as written, from a fresh folder (no cached references).

    python tools/bench_sweep.py [--runs 3] [--set image.width=64 ...]

Runs `torchvol sweep cloud-puff --param march.steps=16,32,64 --param volumes[0].sigma_t=4,12
--out DIR` (plus any --set) --runs times, each into a new temporary folder, and prints each run's
wall time, the median, and the last run's results.csv and verdict. Time it on a quiet machine:
torch's worker threads spin when other jobs share the cores.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

README_SWEEP = ["sweep", "cloud-puff", "--param", "march.steps=16,32,64", "--param", "volumes[0].sigma_t=4,12"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--set", action="append", default=[], metavar="A.B=V", help="an override added to the command")
    args = parser.parse_args()
    torchvol = shutil.which("torchvol", path=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    extra = [a for item in args.set for a in ("--set", item)]
    times, last = [], None
    for run in range(args.runs):
        with tempfile.TemporaryDirectory() as tmp:
            start = time.perf_counter()
            done = subprocess.run([torchvol, *README_SWEEP, *extra, "--out", str(Path(tmp) / "sweep"), "--no-progress"],
                                  capture_output=True, text=True, check=True)
            times.append(time.perf_counter() - start)
            last = (Path(tmp) / "sweep" / "results.csv").read_text(), done.stdout
        print(f"run {run + 1}: {times[-1]:.1f} s", flush=True)
    print(f"median of {len(times)}: {statistics.median(times):.1f} s ({os.cpu_count()} cores)")
    print(last[0] + last[1], end="")


if __name__ == "__main__":
    main()
