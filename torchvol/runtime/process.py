"""The tuning that helps a rendering process, as one call (`tune_process`): importing torchvol
changes nothing in a process, so torchvol's own processes apply it (the `torchvol` command, the
generator's worker processes and Dask workers, `SceneDataset.worker_init_fn`) and a user's own
script may call it too (`tv.tune_process()`).

* OpenMP's threads sleep between parallel regions (``OMP_WAIT_POLICY=PASSIVE``) instead of
  spinning: a render's thousands of small ops otherwise spin against any other busy process, 23×
  slower beside one instead of 1.5× (docs/SPEED.md, "One busy competitor"). libgomp reads the
  variable once, when torch loads: it takes effect only where it is set before anything imports
  torch (and in every process started from this one after it). A user's own setting wins.
* glibc's malloc thresholds raised (`heap.keep_freed_memory`): a march step's freed tensors stay in
  the heap for the next step's, no page faults at every step; the environment's own malloc tuning
  or ``TORCHVOL_HEAP=system`` leave glibc's defaults alone.

`imports_uncollected` is the command's too: torch and torchvol imported with Python's cyclic
collector off, their objects then frozen (`gc.freeze`). The collector's full passes over the
million objects an import of torch makes took 0.22 s of a 1.5 s start (0.13 s inside `import
torch`, 0.09 s inside torchvol's); frozen, no later pass scans them again, in this process or in
the workers it forks (whose pages they then share instead of copying: CPython's advice for a
process that forks).

This module imports no torch: a process may call `tune_process` first thing.
"""

from __future__ import annotations

import gc
import os
import sys
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterator

from . import heap

__all__ = ["Tuned", "WAIT_POLICY", "imports_uncollected", "init_worker", "tune_process"]

# OpenMP's wait policy torchvol's processes run with, unless the environment names one
WAIT_POLICY = "PASSIVE"


@dataclass(frozen=True)
class Tuned:
    """What `tune_process` did: `wait_policy`, the OMP_WAIT_POLICY now in the environment;
    `wait_policy_applies`, whether torch loads after it (False: torch was already imported, its
    OpenMP keeps the policy it started with); `heap`, whether malloc's thresholds were raised."""

    wait_policy: str
    wait_policy_applies: bool
    heap: bool


def tune_process() -> Tuned:
    """Tune this process for rendering: ``OMP_WAIT_POLICY=PASSIVE`` unless the environment sets
    it (effective only before torch is imported: call this first thing), and glibc's malloc
    thresholds raised (`heap.keep_freed_memory`, unless the environment tunes malloc or says
    ``TORCHVOL_HEAP=system``). Safe to call again; -> what it did (`Tuned`)."""
    policy = os.environ.setdefault("OMP_WAIT_POLICY", WAIT_POLICY)
    return Tuned(wait_policy=policy, wait_policy_applies="torch" not in sys.modules, heap=heap.keep_freed_memory())


@contextmanager
def imports_uncollected() -> Iterator[None]:
    """Python's cyclic collector off inside; on leaving, every object alive frozen (`gc.freeze`:
    never scanned again) and the collector as it was. For a process's imports (see the module
    notes); garbage made inside is not collected, so not for work."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        gc.freeze()
        if enabled:
            gc.enable()


def init_worker(threads: int) -> None:
    """A torchvol worker process's initializer (the generator's process pool): `tune_process`
    before the tasks import torch, then torch's intra-op thread count set to `threads`."""
    tune_process()
    import torch  # after the wait policy: libgomp reads it when torch loads

    torch.set_num_threads(threads)
