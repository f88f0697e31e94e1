"""torchvol.heap: freed tensors stay in glibc's heap, so the next step's allocations fault no pages."""

import os
import platform
import subprocess
import sys
import textwrap

import pytest

from torchvol import heap

glibc = pytest.mark.skipif(not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc",
                           reason="mallopt's thresholds are glibc's")

# a march step's pattern: ten 4 MB tensors written, then all freed; page faults per round
ROUNDS = textwrap.dedent("""
    import resource, torch, torchvol

    def rounds(n):
        for _ in range(n):
            tensors = [torch.ones(1 << 20) for _ in range(10)]
            del tensors

    rounds(2)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    rounds(10)
    print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 10)
""")


def faults_per_round(**env) -> float:
    base = {k: v for k, v in os.environ.items() if k not in (*heap.ENVIRONMENT, heap.OPT_OUT)}
    out = subprocess.run([sys.executable, "-c", ROUNDS], env={**base, **env}, check=True, capture_output=True, text=True)
    return float(out.stdout.strip().splitlines()[-1])


@glibc
def test_importing_torchvol_keeps_freed_tensors_in_the_heap():
    # glibc's defaults, fixed by the user's setting or left alone (TORCHVOL_HEAP=system): every 4 MB
    # tensor goes back to the kernel and faults again; after `import torchvol`, none of them does.
    # With 4 KB pages that is 1,024 faults a tensor; with transparent huge pages set to "always" a
    # few 2 MB pages fault instead (a CI machine counted 102.4 a round), so the floor is one a tensor
    tuned = faults_per_round()
    for untuned in (faults_per_round(MALLOC_TRIM_THRESHOLD_="131072"), faults_per_round(TORCHVOL_HEAP="system")):
        assert untuned >= 10, f"untuned heap faulted {untuned} pages a round: the tensors never left it"
        assert tuned < 0.05 * untuned, f"{tuned} faults a round after import torchvol, {untuned} without"


@glibc
def test_the_users_malloc_environment_wins(monkeypatch):
    monkeypatch.setenv("MALLOC_MMAP_THRESHOLD_", "131072")
    assert heap.keep_freed_memory() is False
    monkeypatch.delenv("MALLOC_MMAP_THRESHOLD_")
    monkeypatch.setenv("TORCHVOL_HEAP", "system")
    assert heap.keep_freed_memory() is False
    monkeypatch.delenv("TORCHVOL_HEAP")
    assert heap.keep_freed_memory() is True
