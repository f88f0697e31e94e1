"""Thread counts around blocks and kernels (`torchvol.runtime.threads`)."""

import pytest
import torch

from torchvol.runtime.threads import on_threads, torch_threads


def test_torch_threads_sets_and_restores_the_count_even_on_error():
    before = torch.get_num_threads()
    with torch_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
    with pytest.raises(RuntimeError), torch_threads(1):
        raise RuntimeError("inside")
    assert torch.get_num_threads() == before


def test_on_threads_runs_the_function_on_its_count():
    seen = []
    run = on_threads(lambda x: seen.append(torch.get_num_threads()) or x + 1, 2)
    with torch_threads(1):
        assert run(1) == 2
        assert torch.get_num_threads() == 1
    assert seen == [2]


def test_small_density_kernels_run_on_one_thread(monkeypatch):
    """A compiled kernel's parallel region wakes the second thread at every call (~60 µs): below
    `PARALLEL_POINTS` points that costs more than it saves."""
    from torchvol.noise import fast as fastnoise
    from torchvol.runtime.threads import PARALLEL_POINTS, threads_for

    seen = []

    def recorder(octaves, gain):
        return lambda x, *rest: seen.append(torch.get_num_threads()) or torch.zeros_like(x)

    monkeypatch.setattr(fastnoise, "_compiled_fbm", recorder)
    with torch_threads(2):
        assert threads_for(PARALLEL_POINTS - 1) == 1 and threads_for(PARALLEL_POINTS) == 2
        for n in (5, PARALLEL_POINTS):
            fastnoise.fbm_value_hashed(torch.zeros(n, 3), seed=1, octaves=2, compiled=True)
        assert torch.get_num_threads() == 2
    assert seen == [1, 2]


def test_glue_on_one_thread_hands_kernels_the_callers_count():
    from torchvol.runtime.threads import glue_on_one_thread, kernel_threads

    with torch_threads(2):
        assert kernel_threads() == 2
        with glue_on_one_thread():
            assert torch.get_num_threads() == 1 and kernel_threads() == 2
            with glue_on_one_thread():  # nested: still the outer caller's
                assert torch.get_num_threads() == 1 and kernel_threads() == 2
        assert torch.get_num_threads() == 2 and kernel_threads() == 2
