"""The compile setting (`torchvol.runtime.compilation`): its two modes at the boundary (Dr.Jit's
kernels or the eager reference), anything else refused naming the key, and what a generated
dataset records."""

import json
import re
from pathlib import Path

import numpy as np
import pytest

import torchvol as tv
from torchvol.cli import build_parser
from torchvol.dataset import datasets as data
from torchvol.dataset.generate import generate
from torchvol.runtime.compilation import compile_mode

DATASETS = Path(__file__).resolve().parents[1] / "datasets"
TINY = {"image.width": 6, "image.height": 4}


@pytest.mark.parametrize("value, mode", [(True, "kernels"), (np.bool_(True), "kernels"), ("kernels", "kernels"),
                                         (False, "off"), (np.bool_(False), "off"), (None, "off"), ("off", "off")])
def test_modes_and_bools(value, mode):
    assert compile_mode(value) == mode


# the modes torch.compile had ("exact", "all" and "auto", which chose "exact" for large datasets)
# are gone with it: refused, not quietly read as another
@pytest.mark.parametrize("value", ["auto", "exact", "all", "fast", 1, 0, 0.5])
def test_anything_else_is_refused_naming_the_key_the_value_and_the_choices(value):
    message = f"compile: got {value!r}; expected 'kernels' or 'off' (or True for kernels, False or None for off)"
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        tv.render(tv.preset("voxel-fog", width=4, height=4), compile=value)
    with pytest.raises(ValueError, match=r"^compile: got"):
        data.SceneDataset(DATASETS / "voxel-terrain.toml", 8, compile=value)


def test_scene_dataset_renders_in_its_mode(monkeypatch):
    seen = []
    monkeypatch.setattr(data, "render_samples", lambda *a, **k: seen.append(k["compile"]) or [{}])
    data.SceneDataset(DATASETS / "voxel-terrain.toml", 4, overrides=TINY)[0]
    data.SceneDataset(DATASETS / "voxel-terrain.toml", 4, overrides=TINY, compile=False).batch([1, 2])
    assert seen == ["kernels", "off"]


def test_generate_records_only_the_eager_reference(tmp_path, monkeypatch):
    """meta.json names "eager" for "off" only: the kernels write the canonical bytes, with no key."""
    seen = []
    real = data.render_samples

    def spy(*args, **kwargs):
        seen.append(kwargs["compile"])
        return real(*args, **{**kwargs, "compile": "off"})  # the mode reached the renderer; render eagerly

    monkeypatch.setattr("torchvol.dataset.generate.render_samples", spy)
    recipe = DATASETS / "voxel-terrain.toml"
    for mode, expected in (("kernels", "kernels"), (True, "kernels"), ("off", "off"), (None, "off")):
        seen.clear()
        out = tmp_path / f"{mode}"
        generate(recipe, count=2, out=out, overrides=TINY, progress=False, compile=mode)
        assert set(seen) == {expected}, (mode, seen)
        meta = json.loads((out / "meta.json").read_text())
        assert "compiled" not in meta and meta.get("eager") is (True if expected == "off" else None)
    with pytest.raises(ValueError, match=r"^compile: got 'all'"):
        generate(recipe, count=2, out=tmp_path / "all", overrides=TINY, progress=False, compile="all")


def test_cli_modes(capsys):
    parse = build_parser().parse_args
    for command in (["generate", "r.toml", "--count", "1", "--out", "o"], ["render", "voxel-fog", "--out", "x.png"]):
        assert parse(command).compile == "kernels"
        assert parse(command + ["--eager"]).compile == "off"
        for gone in (["--compile"], ["--compile-mode", "exact"]):  # torch.compile's flags went with it
            with pytest.raises(SystemExit):
                parse(command + gone)
    capsys.readouterr()
