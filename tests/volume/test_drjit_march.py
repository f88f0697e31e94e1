"""The template's march as one Dr.Jit kernel (`torchvol.volume.drjit_march`): its texture noise
and fbm bitwise the torch ones, its march against the eager twin within a stated tolerance (same
steps and evaluations), the same bytes on any thread count and in any batch, and where it runs."""

import multiprocessing
import os

import pytest
import torch
from conftest import assert_close
from hypothesis import given, settings
from hypothesis import strategies as st
from volume.test_fused import (
    VARIANTS,
    _stacked_tables,
    _template,
    assert_same_values,
    hard_points,
)

import torchvol as tv
from torchvol.fields import clouds
from torchvol.noise import lattice as noise
from torchvol.volume import drjit_march, fused

pytestmark = pytest.mark.skipif(not drjit_march.available(torch.zeros(1)), reason="Dr.Jit's LLVM backend is not available")


def _floats(t):
    from drjit.llvm import Float

    return Float(t.numpy())


def _ints(t):
    from drjit.llvm import Int32

    return Int32(t.to(torch.int32).numpy())


def _torch(v):
    import numpy as np

    return torch.from_numpy(np.array(v))


def test_texture_noise_is_the_torch_one_bitwise():
    """`noise.texture_noise_coords` traced by Dr.Jit (one source, `ops.lanes`) gives its torch
    values bitwise, past the float->int32 overflow and at NaN, each point on its own texture of a
    stacked table."""
    _, packed = _stacked_tables([0, 5])
    p = hard_points()
    base = (torch.arange(p.shape[0]) % 2) * 65536
    expected = noise.texture_noise_coords(*p.unbind(1), packed, base.to(torch.int32))
    got = _torch(noise.texture_noise_coords(*(_floats(c.contiguous()) for c in p.unbind(1)), _ints(packed), _ints(base)))
    assert_same_values(got, expected, p)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-3e9, 3e9, allow_nan=False, width=32), min_size=3, max_size=3))
def test_texture_noise_is_bitwise_at_any_float32_point(xyz):
    _, packed = _stacked_tables([3])
    p = torch.tensor([xyz], dtype=torch.float32)
    got = noise.texture_noise_coords(*(_floats(c) for c in p.unbind(1)), _ints(packed), _ints(torch.zeros(1)))
    assert torch.equal(_torch(got), noise.texture_noise_coords(*p.unbind(1), packed))


def test_fbm_with_its_level_of_detail_is_the_eager_one_bitwise():
    _, packed = _stacked_tables([2])
    g = torch.Generator().manual_seed(3)
    p = (torch.rand(30000, 3, generator=g) - 0.5) * 40.0
    count = torch.randint(1, 6, (p.shape[0],), generator=g, dtype=torch.int32)
    base = torch.zeros(p.shape[0], dtype=torch.int32)
    scales = noise.folded_scales(5, dtype=torch.float32, device="cpu")
    from drjit.llvm import Float

    for kept in (None, count):
        expected = clouds.cloud_fbm(*p.unbind(1), packed, base, kept, octaves=5, scales=scales)
        got = clouds.cloud_fbm(*(_floats(c.contiguous()) for c in p.unbind(1)), _ints(packed), _ints(base),
                               None if kept is None else _ints(kept), octaves=5, scales=[Float(float(c)) for c in scales])
        assert torch.equal(_torch(got), expected), f"octaves kept {'all' if kept is None else 'by count'}"


@pytest.mark.parametrize("name", list(VARIANTS))
def test_march_matches_the_eager_twin(name, one_thread):
    """The same ops per ray as the eager twin; Dr.Jit's exp and log2 are its own (an ulp here and
    there), which moves the texture's 8-bit filter by 1/255 at a few points, as inductor's code
    does. Measured, the largest of the variants, the same for inductor's kernels: image 1.5e-4
    (hash dither), alpha 7.4e-5 and depth 1.5e-5 (camera inside the layer). Steps and density
    evaluations are the eager twin's."""
    scene = _template(40, 24, **VARIANTS[name])
    fast, slow = tv.render(scene, compile=True), tv.render(scene)
    assert_close(fast.image, slow.image, atol=2.5e-4, what=f"{name}: image")
    assert_close(fast.alpha, slow.alpha, what=f"{name}: alpha")
    assert_close(fast.depth, slow.depth, what=f"{name}: depth")
    assert fast.stats["march_steps"] == slow.stats["march_steps"], name
    assert fast.stats["density_evals"] == slow.stats["density_evals"], name


def test_march_runs_where_the_torch_kernels_would(monkeypatch, one_thread):
    """`render(..., compile=True)` of the template reaches the Dr.Jit kernel, and not the
    torch.compile kernels."""
    ran = []
    march = drjit_march.march
    monkeypatch.setattr(drjit_march, "march", lambda *a, **k: ran.append(1) or march(*a, **k))
    monkeypatch.setattr(fused, "compiled_steps", lambda *a: pytest.fail("the torch.compile kernels ran"))
    tv.render(_template(12, 8), compile=True)
    assert ran


def test_the_render_runs_torch_on_one_thread_and_the_kernel_on_the_callers(monkeypatch):
    """Every march is the Dr.Jit kernel: torch's ops are glue (rays, compositing, post), run on one
    thread; the kernel gets the caller's count (`threads.glue_on_one_thread`)."""
    import drjit as dr

    from torchvol.runtime.threads import torch_threads

    seen = []
    march = drjit_march.march

    def recording(*args, **kwargs):
        result = march(*args, **kwargs)
        seen.append((torch.get_num_threads(), dr.thread_count()))
        return result

    monkeypatch.setattr(drjit_march, "march", recording)
    with torch_threads(2):
        tv.render(_template(12, 8), compile=True)
        assert torch.get_num_threads() == 2
    assert seen and set(seen) == {(1, 2)}


def test_the_same_bytes_on_any_thread_count_and_in_any_batch():
    scenes = [_template(36, 20), _template(36, 20, time=2.0, **{"volumes.0.density.clouds.texture_seed": 4,
                                                                "camera.eye": [0.3, 0.5, 0.2]})]
    from torchvol.runtime.threads import torch_threads

    with torch_threads(1):
        alone = [tv.render(s, compile=True) for s in scenes]
    with torch_threads(2):
        batch = tv.render(scenes, compile=True)
    for i, one in enumerate(alone):
        for key in ("image", "depth", "alpha"):
            assert torch.equal(getattr(batch, key)[i], getattr(one, key)[0]), f"scene {i}: {key}"
    assert not torch.equal(batch.image[0], batch.image[1])


def test_available_only_for_float32_on_the_cpu_and_not_when_turned_off(monkeypatch):
    assert drjit_march.available(torch.zeros(1))
    assert not drjit_march.available(torch.zeros(1, dtype=torch.float64))
    monkeypatch.setenv(drjit_march.OPT_OUT, "0")
    assert not drjit_march.available(torch.zeros(1))


def _child_render(queue):
    torch.set_num_threads(1)  # as a DataLoader worker does: torch's OpenMP pool does not survive a fork
    out = tv.render(_template(8, 6))
    queue.put((out.stats["plan"]["marches"], out.radiance.numpy().tobytes()))  # bytes: no shared memory to hand over


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork")
def test_a_child_forked_after_drjit_started_renders_with_it_the_same_bytes():
    """A DataLoader worker's default start is a fork: a child forked after its parent started
    Dr.Jit runs the kernels too, and gives the parent's bytes (a sample's bytes must not depend
    on the worker count)."""
    parent = tv.render(_template(8, 6))  # Dr.Jit started in this process
    assert parent.stats["plan"]["marches"] == {"volume0": "drjit"}
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_child_render, args=(queue,))
    child.start()
    marches, radiance = queue.get(timeout=60)
    child.join(60)
    assert child.exitcode == 0
    assert marches == {"volume0": "drjit"} and radiance == parent.radiance.numpy().tobytes()
