"""`torchvol sweep` end to end on tiny scenes and a recipe: rows with their references' bounds,
resuming, voxel keys, figures, verdict."""

import csv
import math
from pathlib import Path

import pytest
from PIL import Image

from torchvol.cli import main
from torchvol.measure.reference import BOUND_FLOOR, reference_overrides
from torchvol.measure.sweep import (
    EVERY_ORDER,
    MEASURED,
    is_approximation,
    split_values,
    sweep,
    verdict,
)

ROOT = Path(__file__).resolve().parents[1]
TINY = ["--set", "image.width=16", "--set", "image.height=12"]
PUFF = ["sweep", "cloud-puff", "--param", "march.steps=4,8", "--param", "volumes[0].sigma_t=5,10", *TINY,
        "--set", "lights[0].shadow.steps=2"]


def read(path: Path) -> list[dict]:
    return list(csv.DictReader(open(path)))


def bounded(row: dict, factor: float = 10.0) -> bool:
    """The row's reference bound is `factor` times under its error, or at the ladder's floor."""
    return float(row["reference_bound"]) * factor <= float(row["rmse"]) or float(row["reference_bound"]) <= BOUND_FLOOR


def test_scene_sweep_end_to_end(tmp_path, capsys, one_thread):
    out = tmp_path / "sweep"
    assert main([*PUFF, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert str(out / "results.csv") in printed and "verdict: " in printed
    rows = read(out / "results.csv")
    assert list(rows[0]) == ["sample", "march.steps", "volumes[0].sigma_t", *MEASURED, *EVERY_ORDER]
    assert len(rows) == 4 and {r["sample"] for r in rows} == {"0"}
    # cloud-puff's octaves: also against every order of scattering, path-traced, its noise bounded
    for r in rows:
        assert float(r["every_order_rel_rmse"]) > 0.02 and 0 < float(r["every_order_bound"]) < float(r["every_order_rmse"]), r
    for r in rows:
        assert float(r["time_s"]) > 0 and int(r["density_evals"]) > 0
        assert float(r["rmse"]) > 0 and math.isfinite(float(r["psnr"])) and bounded(r)
    # more steps, closer to the reference; σ_t changes the scene: a reference each
    err = {(r["march.steps"], r["volumes[0].sigma_t"]): float(r["rmse"]) for r in rows}
    assert err[("8", "10")] < err[("4", "10")] and err[("8", "5")] < err[("4", "5")]
    summary = read(out / "summary.csv")
    assert len(summary) == 4 and all(r["samples"] == "1" and float(r["rmse_std"]) == 0 for r in summary)
    for name in ("contact_sheet.png", "pareto.png", "difference.png", "plot_march.steps.png", "plot_volumes_0_.sigma_t.png"):
        assert Image.open(out / name).format == "PNG", name
    sheet = Image.open(out / "contact_sheet.png")
    assert sheet.size[0] >= 3 * 192  # 4 settings and 2 references, resampled up from 16 px


def test_interrupted_sweep_resumes(tmp_path, one_thread):
    out = tmp_path / "sweep"
    assert main([*PUFF, "--out", str(out), "--no-progress"]) == 0
    rows = read(out / "results.csv")
    references = {p: p.stat().st_mtime_ns for p in (out / "references").glob("*.pt")}
    with open(out / "results.csv", "w") as f:  # killed after two rows, in the middle of the third
        f.write(",".join(rows[0]) + "\n" + "".join(",".join(r.values()) + "\n" for r in rows[:2]) + "0,8,")
    report = sweep("cloud-puff", {"march.steps": [4, 8], "volumes[0].sigma_t": [5, 10]}, out=out,
                   overrides={"image.width": 16, "image.height": 12, "lights[0].shadow.steps": 2})
    again = read(out / "results.csv")
    assert again[:2] == rows[:2] and len(again) == 4  # kept what it measured, measured the rest
    assert [r[k] for r in again[2:] for k in ("rmse", "reference_bound")] == [r[k] for r in rows[2:] for k in ("rmse", "reference_bound")]
    assert {p: p.stat().st_mtime_ns for p in (out / "references").glob("*.pt")} == references  # from the cache
    assert len(report["rows"]) == 4
    with pytest.raises(ValueError, match="^out: .* other settings"):
        sweep("cloud-puff", {"march.steps": [4]}, out=out, overrides={"image.width": 16, "image.height": 12})


def test_recipe_sweep_draws_the_same_samples_for_every_setting(tmp_path, one_thread):
    out = tmp_path / "recipe"
    recipe = ROOT / "datasets" / "clouds.toml"
    assert main(["sweep", str(recipe), "--samples", "4", "--param", "march.steps=4,16", *TINY, "--out", str(out),
                 "--no-progress"]) == 0
    rows = read(out / "results.csv")
    assert [(r["sample"], r["march.steps"]) for r in rows] == [(str(i), s) for i in range(4) for s in ("4", "16")]
    assert all(bounded(r) for r in rows)
    for i in range(4):  # one reference per sample, shared by both settings
        pair = [r for r in rows if r["sample"] == str(i)]
        assert float(pair[1]["rmse"]) < float(pair[0]["rmse"])
    summary = read(out / "summary.csv")
    assert [r["samples"] for r in summary] == ["4", "4"]
    for r, steps in zip(summary, ("4", "16")):
        errors = [float(x["rmse"]) for x in rows if x["march.steps"] == steps]
        assert math.isclose(float(r["rmse_mean"]), sum(errors) / 4) and float(r["rmse_max"]) == max(errors)
        assert float(r["rmse_std"]) > 0 and float(r["time_s_std"]) >= 0  # different clouds, different errors
    with pytest.raises(ValueError, match="^samples: "):  # a recipe draws: how many must be said
        sweep(recipe, {"march.steps": [4]}, out=tmp_path / "x")


def test_voxel_sweep_step_limits_shadows_and_ao(tmp_path, one_thread):
    out = tmp_path / "voxels"
    report = sweep("voxel-terrain", {"voxels.max_steps": [6, 256], "voxels.shadow.steps": [1, 64], "voxels.ao.gamma": [0.5, 1.0]},
                   out=out, overrides={"image.width": 16, "image.height": 12})
    rows = {(r["voxels.max_steps"], r["voxels.shadow.steps"], r["voxels.ao.gamma"]): r for r in report["rows"]}
    assert all(bounded(r) for r in rows.values())
    for gamma in (0.5, 1.0):  # AO changes the scene; step limits only approximate it
        assert rows[6, 64, gamma]["rmse"] > 10 * rows[256, 64, gamma]["rmse"]  # rays stopped after 6 cells: holes
        assert rows[256, 1, gamma]["rmse"] > 10 * rows[256, 64, gamma]["rmse"]  # one-cell shadow rays: lit ground
        assert rows[256, 64, gamma]["rmse"] <= 1e-4
    assert "voxels.max_steps=256, voxels.shadow.steps=64" in report["verdict"]


def test_voxel_sweep_spp_against_the_largest(tmp_path, one_thread):
    report = sweep("voxel-terrain", {"image.spp": [1, 4]}, out=tmp_path / "spp",
                   overrides={"image.width": 16, "image.height": 12})
    one, four = report["rows"]
    assert one["rmse"] > 1e-3 > four["rmse"]  # the reference takes the largest spp, with the same sub-samples


def test_levels_are_starred_settings(tmp_path, one_thread):
    report = sweep("voxel-terrain", {"voxels.shadow.steps": [2]}, levels=["draft", "high"], out=tmp_path / "levels",
                   overrides={"image.width": 16, "image.height": 12})
    assert [(r["voxels.shadow.steps"], r["march.quality"]) for r in report["rows"]] == [(2, ""), ("", "draft"), ("", "high")]


def test_sweep_errors(tmp_path, capsys):
    assert main(["sweep", "cloud-puff", "--param", "march.stepz=4,8", "--out", str(tmp_path)]) == 2
    assert "did you mean 'steps'" in capsys.readouterr().err
    assert main(["sweep", "cloud-puff", "--param", "march.steps", "--out", str(tmp_path)]) == 2
    assert main(["sweep", "cloud-puff", "--param", "march.steps=4", "--samples", "0", "--out", str(tmp_path)]) == 2
    assert "--samples: got 0" in capsys.readouterr().err


def test_value_splitting_key_kinds_and_reference():
    assert split_values("8,16,[1,2,3],{a=1,b=2}") == ["8", "16", "[1,2,3]", "{a=1,b=2}"]
    assert reference_overrides({"march": {"steps": 8, "integrator": "alpha", "max_distance": 9}}) == {
        "integrator": "alpha", "max_distance": 9, "quality": "reference"}
    approximations = ("march.steps", "march.tolerance", "image.spp", "lights.0.shadow.steps", "lights[1].shadow.method",
                      "voxels.max_steps", "voxels.fog.shadow_steps", "sky.atmosphere.light_steps")
    scene = ("march.max_distance", "volumes[0].sigma_t", "image.width", "lights[0].intensity", "voxels.ao.gamma")
    assert all(is_approximation(k) for k in approximations) and not any(is_approximation(k) for k in scene)


def test_verdict_is_the_cheapest_setting_within_the_error_over_every_scene_value():
    def entry(steps, sigma, time_s, rmse):
        return {"march.steps": steps, "volumes[0].sigma_t": sigma, "samples": 1, "time_s_mean": time_s, "rmse_max": rmse,
                "reference_bound_max": rmse / 20}

    keys = ["march.steps", "volumes[0].sigma_t"]
    summary = [entry(16, 4, 1.0, 5e-4), entry(16, 12, 1.0, 3e-3), entry(32, 4, 2.0, 4e-4), entry(32, 12, 2.0, 9e-4),
               entry(64, 4, 4.0, 3e-4), entry(64, 12, 4.0, 5e-4)]
    text = verdict(summary, keys, max_error=1e-3)  # 16 steps fails on σ_t 12: 32 is the cheapest within
    assert text.startswith("cheapest within RMSE 0.001: march.steps=32, 2 s per render, RMSE 0.0009 (worst over every volumes[0].sigma_t)")
    assert verdict(summary, keys, max_error=1e-4).startswith("no setting is within RMSE 0.0001: the most accurate, march.steps=64")
