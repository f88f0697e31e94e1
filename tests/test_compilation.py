"""The compile setting (`torchvol.runtime.compilation`): its modes at the boundary, "auto" by the samples a
process will render (never by what it rendered before), and what a generated dataset records."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

import torchvol as tv
from torchvol.cli import build_parser
from torchvol.dataset import datasets as data
from torchvol.dataset.generate import generate
from torchvol.renderer.plan import batch_mode
from torchvol.runtime import compilation
from torchvol.runtime.compilation import AUTO_COMPILE_SAMPLES, auto_mode, compile_mode

DATASETS = Path(__file__).resolve().parents[1] / "datasets"
TINY = {"image.width": 6, "image.height": 4}


@pytest.mark.parametrize("value, mode", [(True, "all"), (False, "off"), (None, "off"), (1, "all"), (0, "off"),
                                         (np.bool_(True), "all"), ("off", "off"), ("exact", "exact"), ("all", "all"),
                                         ("kernels", "kernels"), ("auto", "kernels")])
def test_modes_and_bools(value, mode):
    assert compile_mode(value) == mode  # one render's "auto" is the Dr.Jit kernels


@pytest.mark.parametrize("value", ["fast", 2, 0.5])
def test_a_bad_mode_names_the_key_and_the_choices(value):
    with pytest.raises(ValueError, match=r"compile.*off, kernels, exact, all, auto"):
        tv.render(tv.preset("voxel-fog", width=4, height=4), compile=value)


def test_auto_compiles_the_exact_kernels_from_the_threshold_on():
    assert auto_mode("auto", AUTO_COMPILE_SAMPLES - 1) == "kernels"
    assert auto_mode("auto", AUTO_COMPILE_SAMPLES) == "exact"
    assert auto_mode("all", 1) == "all" and auto_mode("off", 10**6) == "off"


def test_all_compiles_density_kernels_only_where_they_pay():
    clouds = tv.preset("template-clouds")
    assert batch_mode("all", clouds) == "all"
    assert batch_mode("all", tv.preset("voxel-fog")) == "exact"  # voxels: the exact walk only
    assert batch_mode("exact", clouds) == "exact"


def test_scene_dataset_auto_resolves_from_its_length_whatever_the_process_rendered_before(monkeypatch):
    """ds[i] runs the same whatever the process rendered before: "auto" is "exact" for a dataset
    of AUTO_COMPILE_SAMPLES samples or more, "kernels" below, at its first sample as at its thousandth."""
    seen = []
    monkeypatch.setattr(data, "render_samples", lambda *a, **k: seen.append(k["compile"]) or [{}])
    small = data.SceneDataset(DATASETS / "voxel-terrain.toml", AUTO_COMPILE_SAMPLES - 1, overrides=TINY)
    large = data.SceneDataset(DATASETS / "voxel-terrain.toml", AUTO_COMPILE_SAMPLES, overrides=TINY)
    assert small.compile == large.compile == "auto"
    small[0]
    large[0]
    assert seen == ["kernels", "exact"]
    for k in range(AUTO_COMPILE_SAMPLES):  # a process that has rendered many samples since
        large[k]
    seen.clear()
    small[0]
    small.batch([1, 2])
    large[0]
    assert seen == ["kernels", "kernels", "exact"]
    assert data.SceneDataset(DATASETS / "voxel-terrain.toml", 8, compile=True).compile == "all"
    with pytest.raises(ValueError, match="compile"):
        data.SceneDataset(DATASETS / "voxel-terrain.toml", 8, compile="sometimes")


def test_generate_records_only_the_mode_that_changes_bytes(tmp_path, monkeypatch):
    """meta.json names "compiled" only for "all" and "eager" only for "off"; "kernels" and "exact"
    (what "auto" picks) write the same, canonical bytes."""
    seen = []
    real = data.render_samples

    def spy(*args, **kwargs):
        seen.append(kwargs["compile"])
        return real(*args, **{**kwargs, "compile": "off"})  # the mode reached the renderer; render eagerly

    monkeypatch.setattr("torchvol.dataset.generate.render_samples", spy)
    recipe = DATASETS / "voxel-terrain.toml"
    for mode, count, expected in (("auto", 2, "kernels"), ("auto", AUTO_COMPILE_SAMPLES, "exact"), ("exact", 2, "exact"),
                                  ("all", 2, "all"), ("off", 2, "off")):
        seen.clear()
        out = tmp_path / f"{mode}-{count}"
        generate(recipe, count=count, out=out, overrides=TINY, progress=False, compile=mode,
                 stop_after=1 if count > 2 else None)
        assert set(seen) == {expected}, (mode, count, seen)
        meta = json.loads((out / "meta.json").read_text())
        assert meta.get("compiled") is (True if expected == "all" else None)
        assert meta.get("eager") is (True if expected == "off" else None)
    # resumed, "auto" decides from what is left: fewer than the threshold now
    seen.clear()
    generate(recipe, count=AUTO_COMPILE_SAMPLES, out=tmp_path / f"auto-{AUTO_COMPILE_SAMPLES}", overrides=TINY,
             progress=False, stop_after=1)
    assert set(seen) == {"kernels"}, seen


def test_cli_modes():
    parse = build_parser().parse_args
    base = ["generate", "r.toml", "--count", "1", "--out", "o"]
    assert parse(base).compile == "auto"
    assert parse(base + ["--compile"]).compile == "all"
    assert parse(base + ["--eager"]).compile == "off"
    render = ["render", "voxel-fog", "--out", "x.png"]
    assert parse(render + ["--compile-mode", "exact"]).compile == "exact"
    assert parse(["render", "--compile", "voxel-fog", "--out", "x.png"]).compile == "all"
    assert parse(render).compile == "auto"
    assert parse(render + ["--eager"]).compile == "off"


@pytest.mark.slow
def test_a_kernel_first_called_small_still_runs_on_threads():
    """inductor builds a kernel serial where its first call (the size hint of every later one under
    dynamic shapes) is small, and its cache then serves that serial kernel to every process: a
    16×16 render left all later template renders on one thread. `compiled` asks for dynamic
    threads, so every kernel is a parallel region, whatever the size it was built for."""
    from torch._inductor.utils import run_and_get_code

    def kernel(x):  # a fresh function: torch.compile and `compiled` cache per function
        return torch.sin(x) * 2.0 + 1.0

    tiny = torch.arange(8, dtype=torch.float32)
    with torch._inductor.config.patch(fx_graph_cache=False):
        _, plain = run_and_get_code(torch.compile(kernel, dynamic=True), tiny)
        _, ours = run_and_get_code(compilation.compiled(kernel), tiny)
    assert "omp parallel" not in "".join(plain)  # the trap: without the option a small first call is serial
    assert "#pragma omp parallel" in "".join(ours)
    assert "num_threads(" not in "".join(ours)  # the thread count is OpenMP's when the kernel runs


@pytest.mark.slow
def test_sizes_equal_on_a_first_call_are_not_taken_for_one_size():
    """dynamo's duck sizing builds a first call's equal sizes as one: the template's first light
    call on 3 lit samples (a light direction has 3 coordinates) was built again at the next call,
    ~30 s cold. `compiled` turns it off around its calls, and only there."""
    from torch._dynamo.utils import counters

    # two definitions: dynamo keeps its graphs with a function's code, whichever torch.compile built them
    def kernel(points, direction):
        return points * 2.0, direction + 1.0

    def same_kernel(points, direction):
        return points * 2.0, direction + 1.0

    def graphs(fn) -> int:
        before = counters["stats"]["unique_graphs"]
        fn(torch.ones(3), torch.ones(3))
        fn(torch.ones(7), torch.ones(3))
        return counters["stats"]["unique_graphs"] - before

    with torch._inductor.config.patch(fx_graph_cache=False):
        assert graphs(torch.compile(same_kernel, dynamic=True)) == 2  # the trap: built again for 7 points
        assert graphs(compilation.compiled(kernel)) == 1
    assert torch.fx.experimental._config.use_duck_shape  # the user's own graphs keep torch's default


def test_compile_settings_hold_inside_the_block_only():
    """A render sets dynamo's settings once around a chunk (`compile_settings`), not at each
    kernel call; nested blocks and calls inside keep them, and the user's come back after it."""
    dynamo, shapes = torch._dynamo.config, torch.fx.experimental._config
    before = (dynamo.recompile_limit, shapes.use_duck_shape)
    with compilation.compile_settings():
        inside = (dynamo.recompile_limit, shapes.use_duck_shape)
        with compilation.compile_settings():
            compilation.compiled(torch.neg)(torch.ones(4))
            assert (dynamo.recompile_limit, shapes.use_duck_shape) == inside
        assert (dynamo.recompile_limit, shapes.use_duck_shape) == inside
    assert inside == (compilation.VARIANTS, False)
    assert (dynamo.recompile_limit, shapes.use_duck_shape) == before != inside
