"""torch's intra-op thread count around a block, and Dr.Jit's around a kernel.

With OpenMP's threads asleep between parallel regions (``OMP_WAIT_POLICY=PASSIVE``, as torchvol's
processes run: `process.tune_process`; docs/SPEED.md, "One busy competitor"), each parallel region
wakes them, which on some VMs costs more than a small op's work. A render whose arithmetic is in
Dr.Jit's kernels (on a pool of their own) has only such small ops left in torch, its glue: so the
glue runs on one thread (`glue_on_one_thread`) and each kernel on the caller's count
(`kernel_threads`, `set_drjit_threads`).
"""

from __future__ import annotations

import contextlib
from contextvars import ContextVar

import torch


@contextlib.contextmanager
def torch_threads(threads: int):
    """torch's intra-op thread count set to `threads` inside the block, restored after it."""
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


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
