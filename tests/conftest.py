"""Shared test helpers: one tolerance table keyed by dtype, error reports that say where, and the
hypothesis profiles."""

import os

import pytest
import torch
from hypothesis import settings

# CI gates a landing on one run: there (`HYPOTHESIS_PROFILE=ci`, set by .ci/run) every property
# test draws the same examples each time, so a red CI is the change's defect, not a draw's luck.
# Local runs draw fresh examples and keep finding the hard cases.
settings.register_profile("ci", derandomize=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))

# Absolute tolerances for quantities in [0, 1] (alpha, transmittance, normalised radiance).
TOL = {torch.float32: 1e-4, torch.float64: 1e-9}


def assert_close(actual, expected, *, atol=None, what="value"):
    """Fail with the largest error and its index, not a wall of numbers."""
    actual = torch.as_tensor(actual)
    expected = torch.as_tensor(expected, dtype=actual.dtype).expand_as(actual)
    tol = TOL[actual.dtype] if atol is None else atol
    err = (actual - expected).abs()
    bad = ~torch.isfinite(actual)
    if bad.any():
        idx = tuple(int(i) for i in bad.nonzero()[0])
        raise AssertionError(f"{what}: non-finite value {actual[idx].item()} at {idx}")
    worst = err.max() if err.numel() else torch.tensor(0.0)
    if worst > tol:
        idx = tuple(int(i) for i in torch.nonzero(err == worst)[0])
        raise AssertionError(
            f"{what}: max error {worst.item():.3e} > {tol:.1e} at {idx}: "
            f"got {actual[idx].item():.10g}, expected {expected[idx].item():.10g}"
        )


@pytest.fixture
def one_thread():
    """Run a test with one torch thread (tiny tensors: thread hand-offs cost more than they save,
    badly so on a loaded machine), restoring the count after."""
    from torchvol.runtime.threads import torch_threads

    with torch_threads(1):
        yield


def pytest_configure(config):
    """Under pytest-xdist (`-n auto`), split the CPUs between the workers: each worker's torch
    threads spinning against the other's would make the suite slower, not faster."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1:
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // workers))


def pytest_collection_modifyitems(items):
    """Slow tests first: xdist hands them out before the quick ones, so no worker ends the run
    alone on a long test that started last."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)
