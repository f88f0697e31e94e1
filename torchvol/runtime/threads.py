"""torch's intra-op thread count around a block or a kernel.

With OpenMP's threads asleep between parallel regions (``OMP_WAIT_POLICY=PASSIVE``, as torchvol's
processes run: `process.tune_process`; docs/SPEED.md, "One busy competitor"), each parallel region
wakes them, which on some VMs costs more than a small op's work. A march's eager glue between its compiled kernels (compaction,
gathers, counts over a wavefront) is such small ops; the kernels are where the arithmetic is. So
the glue runs on one thread (`torch_threads`) and each kernel on the caller's threads (`on_threads`),
unless it is small (`threads_for`).
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable
from contextvars import ContextVar

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


# the render's thread count while its torch work runs on one thread (`glue_on_one_thread`)
_KERNEL_THREADS: ContextVar[int | None] = ContextVar("kernel_threads", default=None)


def kernel_threads() -> int:
    """Threads for a kernel on a pool of its own (Dr.Jit's): the caller's count where its torch
    work runs on one thread (`glue_on_one_thread`), else torch's current count."""
    threads = _KERNEL_THREADS.get()
    return torch.get_num_threads() if threads is None else threads


def set_drjit_threads() -> None:
    """Dr.Jit's pool at `kernel_threads()`, before a kernel launches (resized only when it differs)."""
    import drjit as dr

    threads = kernel_threads()
    if dr.thread_count() != threads:
        dr.set_thread_count(threads)


@contextlib.contextmanager
def glue_on_one_thread():
    """torch on one thread inside the block, `kernel_threads` the caller's count: for a render
    whose arithmetic is in kernels on their own pool, torch's ops are glue (rays, compositing,
    post), which a second sleeping thread slows rather than speeds."""
    token = _KERNEL_THREADS.set(kernel_threads())
    try:
        with torch_threads(1):
            yield
    finally:
        _KERNEL_THREADS.reset(token)


def threads_for(points: int) -> int:
    """Threads for a compiled density kernel over `points` points: one below `PARALLEL_POINTS`,
    else torch's current count."""
    return 1 if points < PARALLEL_POINTS else torch.get_num_threads()
