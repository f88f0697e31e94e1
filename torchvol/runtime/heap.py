"""glibc's heap kept for reuse between a render's steps, instead of handed back to the system.

A render allocates and frees tensors of a few MB at every march step (a wavefront's state and
samples). glibc's malloc maps an allocation above its (dynamic) mmap threshold afresh, and hands
the top of its heap back once more than its trim threshold lies free there: either way the next
step's tensors touch new pages, and the kernel faults in and zeroes each one. A template-clouds
render at 640×360 took 21,000-40,000 such page faults, voxel-gi at 128² 36,000; with both
thresholds raised, none, and 5-15% less time (docs/SPEED.md, "The heap").
"""

from __future__ import annotations

import ctypes
import os
import sys

# mallopt's parameters (malloc.h)
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
# allocations below this come from the heap (glibc's largest on 64-bit: 32 MiB); a chunk's
# tensors are at most a few MB, whole images above it still get their own mapping
MMAP_THRESHOLD = 32 << 20
# free memory at the heap's top handed back only beyond this: a step frees ~5 MB, a chunk tens
TRIM_THRESHOLD = 64 << 20
# the user's own glibc tuning wins: the old variables, or any malloc tunable in GLIBC_TUNABLES
ENVIRONMENT = ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TOP_PAD_", "MALLOC_MMAP_MAX_")
TUNABLES, MALLOC_TUNABLE = "GLIBC_TUNABLES", "glibc.malloc."
# TORCHVOL_HEAP=system leaves glibc's defaults alone
OPT_OUT = "TORCHVOL_HEAP"


def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds in this process (`MMAP_THRESHOLD`,
    `TRIM_THRESHOLD`) unless the environment tunes malloc itself or says `TORCHVOL_HEAP=system`;
    -> whether they were set (False off Linux or glibc)."""
    if (not sys.platform.startswith("linux") or any(name in os.environ for name in ENVIRONMENT)
            or MALLOC_TUNABLE in os.environ.get(TUNABLES, "") or os.environ.get(OPT_OUT) == "system"):
        return False
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
        if not hasattr(libc, "gnu_get_libc_version"):  # glibc's own symbol: musl's mallopt does nothing
            return False
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
