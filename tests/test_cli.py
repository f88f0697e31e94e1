"""`torchvol render` end to end: files written, exact float arrays, errors as one line."""

import argparse
import json
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

import torchvol as tv
from torchvol.cli import build_parser, main


def test_render_preset_writes_png_depth_and_arrays(tmp_path, capsys):
    out = tmp_path / "sub" / "clouds.png"
    code = main(["render", "--preset", "template-clouds", "--param", "width=24", "--param", "height=16",
                 "--param", "mouse=[3, 4]", "--out", str(out), "--npy"])
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    assert report["passes"][0] == "rays" and report["density_evals"] > 0
    image = np.asarray(Image.open(out))
    assert image.shape == (16, 24, 3) and image.dtype == np.uint8
    depth_png = Image.open(tmp_path / "sub" / "clouds_depth.png")
    assert np.asarray(depth_png).dtype == np.uint16 and "depth_scale" in depth_png.info
    direct = tv.render(tv.preset("template-clouds", width=24, height=16, mouse=(3, 4)))
    assert np.array_equal(np.load(tmp_path / "sub" / "clouds_depth.npy"), direct.depth[0].numpy())
    assert np.array_equal(image, np.round(direct.image[0].permute(1, 2, 0).numpy() * 255).astype(np.uint8))
    assert np.array_equal(np.load(tmp_path / "sub" / "clouds_K.npy"), direct.camera.K[0].numpy())


def test_render_scene_file_with_overrides(tmp_path):
    scene = tmp_path / "s.toml"
    scene.write_text('[image]\nwidth = 8\nheight = 6\n[[volumes]]\nsigma_t = 2.0\n')
    assert main(["render", str(scene), "--set", "volumes[0].sigma_t=5", "--set", "camera.fov_y=30",
                 "--out", str(tmp_path / "o.png")]) == 0
    assert Image.open(tmp_path / "o.png").size == (8, 6)


@pytest.mark.parametrize(
    "args,needle",
    [
        (["render", "--preset", "nope"], "preset: got 'nope'"),
        (["render", "missing.toml"], "no such scene file"),
        (["render", "--preset", "cloud-puff", "--set", "volumes[0].albedo=2"], "volumes[0].albedo"),
        (["render", "--preset", "cloud-puff", "--set", "nonsense"], "expected KEY=VALUE"),
    ],
)
def test_errors_are_one_line_with_exit_code_2(tmp_path, capsys, args, needle):
    assert main(args + ["--out", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err
    assert needle in err and err.count("\n") == 1 and "Traceback" not in err


def test_console_script_runs():
    done = subprocess.run([sys.executable, "-m", "torchvol.cli", "render", "--help"], capture_output=True, text=True)
    assert done.returncode == 0 and "--preset" in done.stdout


def test_console_script_flushes_its_report_and_keeps_the_exit_code(tmp_path):
    """`command` ends the process without finalisation: what `main` printed and wrote must be out."""
    out = tmp_path / "o.png"
    done = subprocess.run([sys.executable, "-m", "torchvol.cli", "render", "--preset", "cloud-puff", "--param", "width=8",
                           "--param", "height=6", "--out", str(out)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["passes"][0] == "rays" and Image.open(out).size == (8, 6)
    bad = subprocess.run([sys.executable, "-m", "torchvol.cli", "render", "--preset", "no-such", "--out", str(out)],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "no-such" in bad.stderr


def _commands(parser, path=()):
    """(command path, its parser) for every command of the CLI."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _commands(sub, path + (name,))
    if path and not any(isinstance(a, argparse._SubParsersAction) for a in parser._actions):
        yield path, parser


def test_help_describes_every_option_and_lists_the_presets(capsys):
    commands = dict(_commands(build_parser()))
    assert set(commands) == {("render",), ("generate",), ("stats",), ("sweep",), ("bench", "accuracy"), ("bench", "speed")}
    for path, parser in commands.items():
        for action in parser._actions:
            assert action.help, f"torchvol {' '.join(path)} {action.option_strings or action.dest}: no help"
    for command in (["render"], ["sweep"]):
        with pytest.raises(SystemExit):
            main([*command, "--help"])
        text = capsys.readouterr().out
        for name in tv.preset_names():
            assert f"  {name} " in text, name
        assert "sigma_t" in text and "noise_texture" in text and "traversal" in text


def test_an_override_adds_an_optional_table_a_scene_left_out():
    """`--set path.bounces=4` on a preset without `[path]` (its dump holds path = None) adds the
    table, as it adds one that is absent; a bad value is refused naming the key."""
    from torchvol.schema.keypath import set_path

    data = {"path": None, "image": {"width": 8}}
    set_path(data, "path.bounces", 4)
    set_path(data, "atmosphere.steps", 3)
    assert data["path"] == {"bounces": 4} and data["atmosphere"] == {"steps": 3}
    scene = tv.load_scene("cloud-puff", overrides={"path.bounces": 4, "path.samples": 2})
    assert scene.path.bounces == 4 and scene.path.samples == 2
    with pytest.raises(ValueError, match="path.bounces"):
        tv.load_scene("cloud-puff", overrides={"path.bounces": 0})
