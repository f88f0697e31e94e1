"""torch's intra-op thread count around a block or a kernel.

With OpenMP's threads asleep between parallel regions (``OMP_WAIT_POLICY=PASSIVE``, torchvol's
default: docs/SPEED.md, "One busy competitor"), each parallel region wakes them, which on some VMs
costs more than a small op's work. A march's eager glue between its compiled kernels (compaction,
gathers, counts over a wavefront) is such small ops; the kernels are where the arithmetic is. So
the glue runs on one thread (`torch_threads`) and each kernel on the caller's threads (`on_threads`),
unless it is small (`threads_for`).
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable

import torch

# points below which a compiled density kernel runs on one thread: each call of a kernel on two
# PASSIVE threads paid ~60 µs to wake the second (a 4-element add: 15 µs on one, 78 µs on two),
# what a fused fbm takes for ~15,000 points on one thread
PARALLEL_POINTS = 1 << 14


@contextlib.contextmanager
def torch_threads(threads: int):
    """torch's intra-op thread count set to `threads` inside the block, restored after it."""
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def on_threads(fn: Callable, threads: int) -> Callable:
    """`fn` called with torch's thread count set to `threads` (`torch_threads` around each call;
    setting it costs well under a microsecond)."""

    @functools.wraps(fn)
    def run(*args, **kwargs):
        with torch_threads(threads):
            return fn(*args, **kwargs)

    return run


def threads_for(points: int) -> int:
    """Threads for a compiled density kernel over `points` points: one below `PARALLEL_POINTS`,
    else torch's current count."""
    return 1 if points < PARALLEL_POINTS else torch.get_num_threads()
