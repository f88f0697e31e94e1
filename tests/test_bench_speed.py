"""`torchvol bench speed` (torchvol.measure.bench_speed): each section runs and reports, on tiny sizes."""

import pytest

import torchvol as tv
from torchvol.cli import build_parser
from torchvol.measure import bench_speed
from torchvol.runtime import compilation


def test_cli_parses_bench_speed():
    args = build_parser().parse_args(["bench", "speed", "--quick", "--out", "x.md"])
    assert args.quick and args.out == "x.md" and args.func.__name__ == "cmd_bench_speed"
    assert args.parts == list(bench_speed.PARTS)
    assert build_parser().parse_args(["bench", "speed", "--parts", "heap", "render"]).parts == ["heap", "render"]


def test_generation_and_loaded_sections_report(tmp_path):
    rows = bench_speed.generation_rows(["clouds"], workers=(1,), count=8, size=8, cli_count=4)
    assert rows[0]["recipe"] == "clouds" and rows[0]["samples_per_s"] > 0 and rows[0]["bytes_per_sample"] > 0
    # the steady rate is blank (None) where the N extra samples took under a tenth of the 2N run:
    # timing noise on a busy machine (the suite's other workers) can make it so
    steady, first = rows[0]["steady_per_s"], rows[0]["first_s"]
    assert (steady is None and first is None) or (steady > 0 and first >= 0), (steady, first)
    assert rows[0]["cli_wall_s"] > 0 and all(r["cli_wall_s"] is None for r in rows if r["mode"] == "eager")
    loaded = bench_speed.loaded_rows(width=8, height=6, repeat=1, configs=[(1, "PASSIVE", "off")])
    assert loaded[0]["slowdown"] > 0
    heap = bench_speed.heap_rows([("template-clouds", 8, 6, "off", 1)], repeat=1)
    assert [r["heap"] for r in heap] == ["glibc's defaults", "torchvol"]
    assert all(r["seconds"] > 0 and r["faults"] >= 0 and r["system_s"] >= 0 for r in heap)
    text = bench_speed.markdown({"quick": True, "repeat": 1, "generate": rows, "loaded": loaded, "heap": heap})
    assert "| clouds | 1 |" in text and "| 1 | PASSIVE | off |" in text and "fresh CLI, 4 samples" in text
    assert "## The heap" in text and "| template-clouds 8×6 | off | 1 | torchvol |" in text


def test_baseline_times_a_commit_in_its_own_worktree():
    # HEAD's worktree: the committed code, run from its own checkout (not this one's imports)
    rows = bench_speed.baseline_rows(["clouds", "no-such-recipe"], "HEAD", workers=1, count=2, size=8)
    assert [r["recipe"] for r in rows] == ["clouds"], rows  # a recipe the commit lacks is left out
    assert rows[0]["then_s"] > 0 and rows[0]["now_s"] > 0 and rows[0]["gain"] == rows[0]["then_s"] / rows[0]["now_s"]
    text = bench_speed.markdown({"quick": True, "repeat": 1, "baseline": rows})
    assert "## Against `HEAD`'s default" in text and "| clouds |" in text


@pytest.mark.slow  # every preset, eager and in kernels
def test_speed_quick_logic_on_tiny_sizes(tmp_path):
    from torchvol.runtime.compilation import drjit_available

    rows = bench_speed.render_rows(((16, 9),), repeat=1, physical_size=(8, 8))
    drjit = drjit_available()
    kernels = {bench_speed.DEFAULT, f"{bench_speed.DEFAULT}, 1 thread", "table hash, default (Dr.Jit march)"}
    assert {r["renderer"] for r in rows} >= {"torchvol eager", "arithmetic hash, eager"} | (kernels if drjit else set())
    floor = bench_speed.floor_rows(points=2048, repeat=1)
    assert all(r["evals_per_s"] > 0 for r in floor) and {r["density"] for r in floor} == {"cloud-puff", "template-clouds"}
    assert ({bench_speed.FLOORS[d][1] for d in bench_speed.FLOORS} <= {r["kernel"] for r in floor}) == drjit
    assert all((r["x_floor"] is None) == (r["evals_per_s"] is None) for r in rows)
    assert all(r["x_floor"] > 0 for r in rows if r["x_floor"] is not None)
    # homogeneous-box: a closed form, few ops (turning a march's 2e5 profiler events into rows takes ~10 s)
    profile = {"homogeneous-box 8×8": bench_speed.profile_rows("homogeneous-box", size=8, top=3)}
    assert all(len(rows) == 3 and all(0 < r["share"] <= 1 for r in rows) for rows in profile.values())
    generation = bench_speed.generation_rows(["clouds"], workers=(1,), count=1, size=8)
    # clouds march in the Dr.Jit kernel by default: the default and the eager reference
    assert [r["mode"] for r in generation] == (["default", "eager"] if drjit else ["default"])
    presets = bench_speed.preset_rows(size=8, repeat=1, floor_points=2048)
    by_name = {r["preset"]: r for r in presets}
    assert set(by_name) == set(tv.preset_names()) and by_name["homogeneous-box"]["marches"] == "closed_form"
    if drjit:  # a preset whose march is a kernel has its eager time and its floor
        assert by_name["cloud-puff"]["marches"] == "drjit" and by_name["cloud-puff"]["eager_s"] > 0
        assert by_name["cloud-puff"]["x_floor"] > 0 and by_name["template-clouds"]["x_floor"] > 0
        assert by_name["cloudscape"]["marches"] == "drjit" and by_name["cloudscape"]["x_floor"] > 0  # its layer's floor
        # the part of × floor its kernels ran: some, never more than the whole
        assert all(0 < r["x_floor_kernels"] <= r["x_floor"] for r in presets if r["x_floor"] is not None)
        # and against the floor on its own points (every preset with a floor but the template's)
        assert by_name["cloud-puff"]["x_floor_own"] > 0 and by_name["template-clouds"]["x_floor_own"] is None
    text = bench_speed.markdown({"quick": True, "repeat": 1, "profile": profile, "render": rows, "floor": floor,
                                 "presets": presets, "preset_size": 8, "generate": generation})
    assert "## Where the time goes" in text and "## Renders" in text and "## The floor" in text
    assert "## Presets: the default render, 8×8" in text and "| cloud-puff |" in text
    assert "| clouds | 1 | default |" in text


@pytest.mark.parametrize("preset, expected", [(None, "PASSIVE"), ("ACTIVE", "ACTIVE")])
def test_openmp_waits_passively_unless_the_user_says_otherwise(preset, expected):
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if preset:
        env["OMP_WAIT_POLICY"] = preset
    code = "import torchvol, os; torchvol.tune_process(); import torch; print(os.environ['OMP_WAIT_POLICY'])"
    out = subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True, text=True)
    assert out.stdout.strip() == expected


def test_floor_ratio_pairs_each_render_with_the_floor_run_beside_it():
    # 100 evaluations at 100 points in 0.5 s: the floor takes 0.5 s, a render of 1 s is 2x it
    assert bench_speed.floor_ratio([1.0], [0.5], evals=100, points=100) == 2.0
    # run by run, not medians apart: a machine twice as slow in the second run slows both
    assert bench_speed.floor_ratio([1.0, 2.0, 1.0], [0.5, 1.0, 0.25], evals=100, points=100) == 2.0
    assert bench_speed.floor_ratio([3.0], [1.0], evals=50, points=100) == 6.0


def test_time_render_runs_the_floor_after_each_render():
    calls = []
    floor = bench_speed.Floor(kernel=lambda: calls.append(1), points=10, threads=1)
    timing = bench_speed.time_render("homogeneous-box", compile=False, repeat=3, floor=floor)
    assert len(calls) == 3 and timing.seconds > 0 and timing.first_s > 0 and timing.evals > 0 and timing.x_floor > 0
    assert bench_speed.time_render("homogeneous-box", compile=False, repeat=1).x_floor is None  # no floor given
    # eagerly no kernel runs: a floor's kernels' part is 0 (or None where Dr.Jit cannot run)
    assert timing.x_floor_kernels in (0.0, None)


@pytest.mark.skipif(not compilation.drjit_available(), reason="needs Dr.Jit's LLVM backend")
def test_kernel_seconds_are_the_kernels_time_within_the_call():
    scene = tv.preset("cloud-puff", width=16, height=16)
    tv.render(scene)
    seconds, kernels = bench_speed.kernel_seconds(lambda: tv.render(scene))
    assert 0 < kernels <= seconds
    assert bench_speed.kernel_seconds(lambda: None)[1] == 0.0  # nothing launched: its history empty


def test_recording_points_keeps_every_evaluation_of_a_render_in_order():
    """`renderer.stats.recording_points`: the points each volume's field evaluated (what the
    bench's floor on a render's own points runs), as many as the render counts, each a copy."""
    from torchvol.renderer.stats import recording_points

    scene = tv.preset("multi-layer", width=12, height=9)
    with recording_points() as record:
        out = tv.render(scene, compile="off", keep_context=True)
    by_volume = {vol.plan.name: sum(p.shape[0] for p, _, _ in record.get(vol.field, [])) for vol in out.context.volumes}
    assert by_volume == out.stats["density_evals_by_volume"] and sum(by_volume.values()) == out.stats["density_evals"]
    assert all(p.shape[1] == 3 and s.shape == p.shape[:1] for calls in record.values() for p, s, _ in calls)
    with recording_points() as again:
        pass
    assert again == {} and tv.render(scene, compile="off").stats["density_evals"] == out.stats["density_evals"]
