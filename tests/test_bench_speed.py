"""`torchvol bench speed` (torchvol.bench_speed): each section runs and reports, on tiny sizes."""

import pytest

from torchvol import bench_speed
from torchvol.cli import build_parser


def test_cli_parses_bench_speed():
    args = build_parser().parse_args(["bench", "speed", "--quick", "--out", "x.md"])
    assert args.quick and args.out == "x.md" and args.func.__name__ == "cmd_bench_speed"


def test_generation_and_loaded_sections_report(tmp_path):
    rows = bench_speed.generation_rows(["clouds"], workers=(1,), count=1, size=8, compiled=False)
    assert rows[0]["recipe"] == "clouds" and rows[0]["samples_per_s"] > 0 and rows[0]["bytes_per_sample"] > 0
    assert rows[0]["steady_per_s"] > 0 and rows[0]["first_s"] >= 0
    loaded = bench_speed.loaded_rows(width=8, height=6, repeat=1, configs=[(1, "PASSIVE")])
    assert loaded[0]["slowdown"] > 0
    text = bench_speed.markdown({"quick": True, "repeat": 1, "generate": rows, "loaded": loaded})
    assert "| clouds | 1 |" in text and "| 1 | PASSIVE |" in text


@pytest.mark.slow  # compiles the template's and the fused fbm's kernels (tens of seconds on 2 cores, once)
def test_speed_quick_logic_on_tiny_sizes(tmp_path):
    rows = bench_speed.render_rows(((16, 9),), repeat=1, physical_size=(8, 8))
    assert {r["renderer"] for r in rows} >= {"torchvol eager", "torchvol torch.compile", "arithmetic hash, fused field compiled"}
    floor = bench_speed.floor_rows(points=2048, repeat=1)
    assert all(r["evals_per_s"] > 0 for r in floor) and {r["density"] for r in floor} == {"cloud-puff", "template-clouds"}
    assert all(f is None or f > 0 for f in bench_speed.floor_ratios(rows, floor))
    # homogeneous-box: a closed form, few ops (turning a march's 2e5 profiler events into rows takes ~10 s)
    profile = {"homogeneous-box 8×8": bench_speed.profile_rows("homogeneous-box", size=8, top=3)}
    profile["fused"] = bench_speed.profile_rows("cloud-puff", size=8, top=3, hash="arithmetic", compile=True)
    assert all(len(rows) == 3 and all(0 < r["share"] <= 1 for r in rows) for rows in profile.values())
    generation = bench_speed.generation_rows(["clouds"], workers=(1,), count=1, size=8)
    assert [r["mode"] for r in generation] == ["eager", "compiled"]
    text = bench_speed.markdown({"quick": True, "repeat": 1, "profile": profile, "render": rows, "floor": floor,
                                 "generate": generation})
    assert "## Where the time goes" in text and "## Renders" in text and "## The floor" in text
    assert "| clouds | 1 | compiled |" in text


@pytest.mark.parametrize("preset, expected", [(None, "PASSIVE"), ("ACTIVE", "ACTIVE")])
def test_openmp_waits_passively_unless_the_user_says_otherwise(preset, expected):
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if preset:
        env["OMP_WAIT_POLICY"] = preset
    code = "import torchvol, os, torch; print(os.environ['OMP_WAIT_POLICY'])"
    out = subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True, text=True)
    assert out.stdout.strip() == expected


def test_floor_ratio_is_time_over_the_fastest_kernel_of_the_same_density():
    render = [dict(work="template-clouds 16×9", evals_per_s=None), dict(work="template-clouds 16×9", evals_per_s=10.0),
              dict(work="cloud-puff 8×8", evals_per_s=50.0)]
    floor = [dict(density="template-clouds", evals_per_s=40.0), dict(density="template-clouds", evals_per_s=20.0),
             dict(density="cloud-puff", evals_per_s=100.0)]
    assert bench_speed.floor_ratios(render, floor) == [None, 4.0, 2.0]
    # a one-thread render against the one-thread kernel, not the fastest on any thread count
    one = [dict(work="template-clouds 16×9", evals_per_s=10.0, threads=1)]
    floors = [dict(density="template-clouds", evals_per_s=40.0, threads=2),
              dict(density="template-clouds", evals_per_s=25.0, threads=1)]
    assert bench_speed.floor_ratios(one, floors) == [2.5]
