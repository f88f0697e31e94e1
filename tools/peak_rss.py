"""Peak memory of one large render: renders a bundled preset at size×size in a fresh Python process
and reports that process's peak RSS and wall time, with the size of the output tensors for context.

Guards the requirement that a 4096×4096 render stays under 2 GB: `render` marches `chunk_rays` rays
at a time, so its peak should be the full-frame outputs plus one chunk's working set, not a
frame-sized working set.

    PYTHONPATH=. python tools/peak_rss.py [--size 4096] [--preset homogeneous-box]
                                          [--chunk-rays 65536] [--threads 1] [--limit-gb 2]

Exits 1 when the peak RSS is above --limit-gb (GB = 10^9 bytes). The figure is the child's
ru_maxrss (KiB on Linux) as os.wait4 returns it: getrusage(RUSAGE_CHILDREN) for that one child,
since RUSAGE_CHILDREN itself is the maximum over every child ever reaped (under pytest, other
tests' subprocesses too). A fresh process keeps imports and earlier work in the caller out of it.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import torch

import torchvol as tv
from torchvol.renderer.executor import DEFAULT_CHUNK_RAYS

ROOT = Path(__file__).resolve().parents[1]


def render_here(*, preset: str, size: int, chunk_rays: int, threads: int) -> dict:
    """Render once in this process: seconds in `render` and bytes held by its outputs."""
    torch.set_num_threads(threads)
    scene = tv.preset(preset, width=size, height=size)
    start = time.perf_counter()
    out = tv.render(scene, chunk_rays=chunk_rays)
    seconds = time.perf_counter() - start
    tensors = [out.image, out.radiance, out.depth, out.alpha, *out.aovs.values()]
    return {"render_s": seconds, "output_bytes": sum(t.numel() * t.element_size() for t in tensors)}


def measure(*, preset: str = "homogeneous-box", size: int = 4096, chunk_rays: int = DEFAULT_CHUNK_RAYS,
            threads: int = 1) -> dict:
    """`render_here` in a fresh subprocess: its peak RSS (bytes), wall time (with imports), render
    time and output bytes."""
    cmd = [sys.executable, __file__, "--in-process", "--preset", preset, "--size", str(size),
           "--chunk-rays", str(chunk_rays), "--threads", str(threads)]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    start = time.perf_counter()
    with subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True, env=env) as proc:
        stdout = proc.stdout.read()
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        raise RuntimeError(f"render subprocess exited with {proc.returncode}: {' '.join(cmd)}")
    return {"peak_rss_bytes": usage.ru_maxrss * 1024, "wall_s": wall, **json.loads(stdout)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=4096, help="image width and height (default 4096)")
    ap.add_argument("--preset", default="homogeneous-box", choices=tv.preset_names())
    ap.add_argument("--chunk-rays", type=int, default=DEFAULT_CHUNK_RAYS)
    ap.add_argument("--threads", type=int, default=1, help="torch threads in the render (default 1)")
    ap.add_argument("--limit-gb", type=float, default=2.0, help="exit 1 above this peak RSS (default 2)")
    ap.add_argument("--in-process", action="store_true",
                    help="render in this process and print one JSON line (what the fresh subprocess runs)")
    args = ap.parse_args(argv)
    options = {"preset": args.preset, "size": args.size, "chunk_rays": args.chunk_rays, "threads": args.threads}
    if args.in_process:
        print(json.dumps(render_here(**options)))
        return 0
    m = measure(**options)
    print(f"{args.preset} {args.size}×{args.size}, chunk_rays {args.chunk_rays}, {args.threads} thread(s)")
    print(f"peak RSS  {m['peak_rss_bytes'] / 1e9:.2f} GB ({m['peak_rss_bytes'] // 1024:,} KiB), limit {args.limit_gb:g} GB")
    print(f"wall      {m['wall_s']:.1f} s (render {m['render_s']:.1f} s, the rest imports and startup)")
    print(f"outputs   {m['output_bytes'] / 1e9:.2f} GB (image, radiance, depth, alpha, aovs)")
    return 1 if m["peak_rss_bytes"] > args.limit_gb * 1e9 else 0


if __name__ == "__main__":
    sys.exit(main())
