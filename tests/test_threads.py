"""Thread counts around blocks and kernels (`torchvol.runtime.threads`)."""

import pytest
import torch

from torchvol.runtime.threads import torch_threads


def test_torch_threads_sets_and_restores_the_count_even_on_error():
    before = torch.get_num_threads()
    with torch_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
    with pytest.raises(RuntimeError), torch_threads(1):
        raise RuntimeError("inside")
    assert torch.get_num_threads() == before


def test_glue_on_one_thread_hands_kernels_the_callers_count():
    from torchvol.runtime.threads import glue_on_one_thread, kernel_threads

    with torch_threads(2):
        assert kernel_threads() == 2
        with glue_on_one_thread():
            assert torch.get_num_threads() == 1 and kernel_threads() == 2
            with glue_on_one_thread():  # nested: still the outer caller's
                assert torch.get_num_threads() == 1 and kernel_threads() == 2
        assert torch.get_num_threads() == 2 and kernel_threads() == 2
