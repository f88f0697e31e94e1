"""`torchvol bench accuracy` end to end on tiny images, and the quality levels it reports."""

import re

import pytest
import torch
from PIL import Image

import torchvol as tv
from torchvol.cli import main
from torchvol.measure.bench_accuracy import FIXED_STEPS, TECHNIQUES, accuracy
from torchvol.measure.reference import BOUND_FLOOR, at_quality, image_error
from torchvol.scene.quality import QUALITY, at_level, march_settings

PHYSICAL = {  # a shadowed fbm cloud filling the frame (no silhouette: level errors are march errors)
    "image": {"width": 6, "height": 4},
    "camera": {"eye": [0.0, 0.0, -1.5], "target": [0.0, 0.0, 0.0], "fov_y": 30.0},
    "sky": {"kind": "constant", "radiance": [0.3, 0.45, 0.7]},
    "lights": [{"direction": [0.5, 0.8, -0.6], "intensity": 6.0, "shadow": {}}],
    "volumes": [{"bounds": {"box": {"min": [-1.0, -1.0, -1.0], "max": [1.0, 1.0, 1.0]}}, "sigma_t": 3.0, "albedo": 0.9,
                 "density": {"fbm": {"octaves": 1, "frequency": 1.0, "bias": 0.5}}}],
}


def _table(path, index: int = 0):
    """The `index`-th Markdown table of the report, as rows of cells."""
    tables = path.read_text().split("\n\n")
    tables = [t for t in tables if t.startswith("| ")]
    return [[c.strip() for c in line.strip("|").split("|")] for line in tables[index].splitlines() if line.startswith("| ")]


def test_bench_accuracy_writes_table_and_plot(tmp_path, capsys, one_thread):
    out = tmp_path / "bench"
    assert main(["bench", "accuracy", "--out", str(out), "--width", "16", "--height", "12", "--repeat", "1",
                 "--scenes", "voxel-terrain", "--knobs", "spp,shadow_steps"]) == 0
    header, _, *rows = _table(out / "accuracy.md")
    assert header == ["scene", "knob", "setting", "time (s)", "rel. RMSE", "± reference bound", "PSNR (dB)",
                      "rel. RMSE against every order"]
    assert all(r[7] == "" for r in rows)  # voxels: no path-traced reference
    assert {r[0] for r in rows} == {"voxel terrain"}
    got = [(r[1], r[2]) for r in rows]
    assert got == ([("shadow_steps", v) for v in ("8", "16", "32", "64", "128")] + [("spp", v) for v in ("1", "2", "4")]
                   + [("level", q) for q in QUALITY])
    assert all(float(r[3]) > 0 for r in rows)
    # every error has its reference's bound beside it, 10x under the smallest error or at the floor
    line = next(line for line in (out / "accuracy.md").read_text().splitlines() if line.startswith("- voxel terrain: reference rung"))
    bound, under = re.search(r"its bound \(RMSE (\S+)\) is (\S+)× under the smallest error of its rows", line).groups()
    assert float(under) >= 10 or float(bound) <= BOUND_FLOOR
    assert len({r[5] for r in rows}) == 1  # one reference for the scene's rows
    assert Image.open(out / "accuracy.png").format == "PNG"
    # what each technique costs, per pass, in every report
    header, _, *costs = _table(out / "accuracy.md", 1)
    assert header[0] == "preset" and [r[0] for r in costs] == list(TECHNIQUES)
    assert all(float(r[1]) > 0 and r[3] for r in costs), costs
    # a second run into the same folder reuses the stored references instead of rendering them again
    stored = {p: p.stat().st_mtime_ns for p in (out / "references").glob("render-*.pt")}
    assert len(stored) >= 2  # a rung and the one under it, which bounds its error
    assert main(["bench", "accuracy", "--out", str(out), "--width", "16", "--height", "12", "--repeat", "1",
                 "--scenes", "voxel-terrain", "--knobs", "spp"]) == 0
    assert {p: p.stat().st_mtime_ns for p in (out / "references").glob("render-*.pt")} == stored
    again = _table(out / "accuracy.md")[2:]
    assert [r[4:] for r in again if r[1] == "level"] == [r[4:] for r in rows if r[1] == "level"]  # the same errors


def test_bench_bad_input(tmp_path, capsys):
    assert main(["bench", "accuracy", "--out", str(tmp_path), "--knobs", "stepz"]) == 2
    err = capsys.readouterr().err
    assert "--knobs: got 'stepz'" in err and "did you mean 'steps'" in err
    assert main(["bench", "accuracy", "--out", str(tmp_path), "--scenes", "cloud-puf"]) == 2
    assert "--scenes: got 'cloud-puf'" in capsys.readouterr().err
    with pytest.raises(ValueError, match="^width: got 0"):  # the library names its parameters
        accuracy(tmp_path, width=0)


def test_levels_are_ordered_on_a_physical_scene(one_thread):
    reference = tv.render(at_quality(PHYSICAL, "reference"))
    assert reference.stats["dtype"] == "float64"
    errors = [image_error(tv.render(at_quality(PHYSICAL, q)).image, reference.image)["rel_rmse"]
              for q in ("draft", "default", "high")]
    assert errors[0] >= errors[1] >= errors[2] > 0, errors


def test_explicit_keys_win_over_the_level():
    terrain = tv.preset("voxel-terrain", width=8, height=6)
    for quality, level in QUALITY.items():
        given = at_level(tv.load_scene(PHYSICAL, {"march.quality": quality, "lights[0].shadow.steps": 5,
                                                   "image.spp": 3, "march.steps": 7}))
        assert (given.lights[0].shadow.steps, given.image.spp, march_settings(given.march).rule.steps) == (5, 3, 7)
        assert march_settings(given.march).dtype == level.dtype
        implied = at_level(tv.load_scene(PHYSICAL, {"march.quality": quality}))
        assert (implied.lights[0].shadow.steps, implied.image.spp) == (level.shadow_steps, level.spp)
        assert march_settings(implied.march).rule.steps == level.steps
        assert at_level(tv.load_scene(terrain, {"march.quality": quality})).voxels.shadow.steps == 64  # the preset's
        bare = at_quality(terrain.model_dump(), quality)
        assert at_level(tv.load_scene(bare)).voxels.shadow.steps == level.voxel_shadow_steps


def test_default_level_keeps_former_defaults():
    """Scenes that relied on the schema's former fixed defaults render as before at `default`."""
    scene = at_level(tv.load_scene({**PHYSICAL, "voxels": None}))
    assert (scene.image.spp, scene.lights[0].shadow.steps) == (1, 16)
    default = QUALITY["default"]
    assert (default.voxel_shadow_steps, default.voxel_max_steps, default.fog_shadow_steps, default.atmosphere_steps) == (32, 256, 16, (16, 8))


def test_levels_fill_voxel_and_sky_step_limits_and_explicit_keys_win():
    fog = tv.load_scene(tv.preset("voxel-fog", width=8, height=6).model_dump(), {})
    bare = at_quality(fog.model_dump(), "reference")
    bare["sky"] = {"kind": "atmosphere"}
    for quality, level in QUALITY.items():
        bare["march"]["quality"] = quality
        filled = at_level(tv.load_scene(bare))
        assert (filled.voxels.max_steps, filled.voxels.fog.shadow_steps) == (level.voxel_max_steps, level.fog_shadow_steps)
        assert (filled.sky.atmosphere.steps, filled.sky.atmosphere.light_steps) == level.atmosphere_steps
        given = at_level(tv.load_scene(bare, {"voxels.max_steps": 77, "voxels.fog.shadow_steps": 5, "sky.atmosphere.steps": 3}))
        assert (given.voxels.max_steps, given.voxels.fog.shadow_steps, given.sky.atmosphere.steps) == (77, 5, 3)
        assert given.sky.atmosphere.light_steps == level.atmosphere_steps[1]
        assert at_level(filled) == filled  # idempotent


def test_reference_renders_in_float64():
    out = tv.render(at_quality(tv.preset("voxel-terrain", width=8, height=6).model_dump(), "reference"))
    assert out.stats["dtype"] == "float64" and out.image.dtype == torch.float32


@pytest.mark.slow
def test_bench_tolerance_table_in_the_tolerance_units(tmp_path, one_thread):
    out = tmp_path / "bench"
    assert main(["bench", "accuracy", "--out", str(out), "--width", "8", "--height", "6", "--repeat", "1",
                 "--scenes", "cloud-puff", "--knobs", "tolerance"]) == 0
    text = (out / "accuracy.md").read_text()
    section = text.split("## Error-controlled marching")[1].splitlines()
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in section if line.startswith("| physical clouds")]
    assert [r[1] for r in rows] == [f"{n} steps" for n in FIXED_STEPS] + ["tolerance 0.01", "tolerance 0.001", "tolerance 0.0001"]
    fixed, adaptive = rows[:len(FIXED_STEPS)], rows[len(FIXED_STEPS):]
    assert all(r[5] == "" for r in fixed) and all(float(r[5]) > 0 for r in adaptive)  # only the tolerance march estimates

    def error(cell: str) -> tuple[float, float]:  # "1.8e-04 ± 3e-07": the error and its reference's bound
        value, bound = cell.split(" ± ")
        return float(value), float(bound)

    assert error(fixed[-1][3])[0] < error(fixed[0][3])[0] and error(fixed[-1][4])[0] < error(fixed[0][4])[0]  # more steps, less error
    assert all(error(r[c])[1] < error(fixed[0][c])[0] / 10 for r in rows for c in (3, 4))
    verdicts = [line for line in section if line.startswith("- physical clouds, tolerance")]
    assert len(verdicts) == 3 and all(("tolerance holds" in v or "tolerance does NOT hold" in v) and " s, where " in v for v in verdicts)
