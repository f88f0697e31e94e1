"""`torchvol bench accuracy`: error against time on the bundled scenes, per knob and per quality level.

Each knob is a curve: the scene as bundled with one setting changed (primary steps, integrator,
shadow steps, LOD, spp, torch.compile). Each quality level is one row: the scene with every key the
level decides removed (`sweep.at_quality`). Error is against the `reference` level render of the same
scene (relative RMSE and PSNR, `sweep.image_error`); time is the median wall time of `repeat` renders
(a compiled render's first call, which compiles, is not counted; the reference is timed once). Writes DIR/accuracy.md (a
Markdown table) and DIR/accuracy.png (error against time, one panel per scene). For physical scenes
the `tolerance` knob adds a second table to accuracy.md: `march.tolerance` against fixed step counts
in the tolerance's own units (radiance over the light, alpha), against the reference march of the
same rays, with whether each tolerance held and what the cheapest as-accurate fixed count took. References are kept
in DIR/references/, keyed by a hash of the reference scene and seed: a re-run into the same DIR
(another knob, more repeats) reuses them instead of re-rendering the slowest part of the report.
"""

from __future__ import annotations

import hashlib
import json
import math
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import torch

from .quality import QUALITY, Quality, at_level
from .presets import preset_dict
from .render import render
from .scene import load_scene
from .sweep import at_quality, image_error
from .validate import did_you_mean, fail

# report name -> bundled preset
SCENES = {"template clouds": "template-clouds", "physical clouds": "cloud-puff", "voxel terrain": "voxel-terrain"}
# the tolerance table: error-controlled marching against fixed step counts
TOLERANCES = (1e-2, 1e-3, 1e-4)
FIXED_STEPS = (32, 48, 64, 96, 128, 160, 192, 256, 384, 512, 768)  # fine enough that "as accurate" is a fair match
NO_EARLY_EXIT = {"march.min_transmittance": 1e-12}  # early termination leaves an error floor of its own


@dataclass(frozen=True)
class Setting:
    """One point of a knob's curve: scene key overrides ({key path: value}) and the compile flag."""

    label: str
    overrides: dict[str, Any] = field(default_factory=dict)
    compile: bool = False


def _values(key: str, values: Sequence[Any]) -> list[Setting]:
    return [Setting(f"{value}", {key: value}) for value in values]


def is_physical(preset: str) -> bool:
    """Whether a report scene is physically shaded: integrator and `march.tolerance` apply to it."""
    return preset == "cloud-puff"


def knobs(preset: str) -> dict[str, list[Setting]]:
    """The knobs that apply to `preset`, each a list of settings over the scene as bundled."""
    volumes, voxels = preset != "voxel-terrain", preset == "voxel-terrain"
    physical = is_physical(preset)
    out: dict[str, list[Setting]] = {}
    if volumes:
        out["steps"] = _values("march.steps", [16, 32, 64, 128, 256])
    if physical:  # the template's alpha integrator is its look, not an approximation
        out["integrator"] = _values("march.integrator", ["alpha", "riemann", "frostbite"])
        out["shadow_steps"] = _values("lights[0].shadow.steps", [2, 4, 8, 16, 32])
    if voxels:
        out["shadow_steps"] = _values("voxels.shadow.steps", [8, 16, 32, 64, 128])
    if volumes:
        out["lod"] = [Setting("off", {"march.lod": None}), Setting("on", {"march.lod": {"scale": 0.5}})]
    out["spp"] = _values("image.spp", [1, 2, 4])
    out["compile"] = [Setting("off"), Setting("on", compile=True)]
    return out


# the curves of the main table, and `tolerance`: a table of its own, in the tolerance's units (`tolerance_rows`)
KNOBS = ("steps", "integrator", "shadow_steps", "lod", "spp", "compile", "tolerance")


def scene_data(preset: str, *, width: int, height: int, quality: Quality | None = None) -> dict:
    """The preset's scene dict at `width`×`height`; at `quality` (the level's keys removed) if given."""
    data = preset_dict(preset, width=width, height=height)
    return data if quality is None else at_quality(data, quality)


def measure(data: dict, reference: torch.Tensor, setting: Setting, *, repeat: int, seed: int = 0) -> dict[str, float]:
    """Median render time of `repeat` renders of `data` with `setting`, and the image's error
    against `reference` (B, 3, H, W)."""
    scene = load_scene(data, setting.overrides)
    if setting.compile:
        render(scene, seed=seed, compile=True)  # compilation is not what is measured
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        out = render(scene, seed=seed, compile=setting.compile)
        times.append(time.perf_counter() - start)
    return {"time_s": statistics.median(times), **image_error(out.image, reference)}


def reference_render(data: dict, *, seed: int, cache: Path | None, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """The reference render of scene dict `data` (with key `overrides`): {"image", "radiance",
    "alpha", "time_s"}, from `cache` (a folder) when it holds one for exactly this scene, overrides
    and seed, else rendered (and stored there)."""
    overrides = overrides or {}
    key = hashlib.sha256(json.dumps([data, overrides, seed], sort_keys=True, default=repr).encode()).hexdigest()[:16]
    path = None if cache is None else cache / f"reference-{key}.pt"
    if path is not None and path.is_file():
        return torch.load(path)
    start = time.perf_counter()
    out = render(load_scene(data, overrides), seed=seed)
    stored = {"image": out.image, "radiance": out.radiance, "alpha": out.alpha, "time_s": time.perf_counter() - start}
    if path is not None:
        cache.mkdir(parents=True, exist_ok=True)
        partial = path.with_suffix(".partial")
        torch.save(stored, partial)
        partial.replace(path)  # a killed run leaves no half-written reference behind
    return stored


def scene_rows(name: str, *, width: int, height: int, repeat: int, knob_names: Sequence[str], seed: int = 0,
               cache: Path | None = None) -> list[dict]:
    """Rows (scene, knob, setting, time_s, rmse, rel_rmse, psnr) of one report scene: every
    applicable knob in `knob_names`, then one row per quality level. The `reference` row is the
    reference render itself, timed once (the slowest render of the report; its error is 0), kept in
    `cache` when given."""
    preset = SCENES[name]
    stored = reference_render(scene_data(preset, width=width, height=height, quality="reference"), seed=seed, cache=cache)
    reference = stored["image"]
    reference_row = {"scene": name, "knob": "level", "setting": "reference", "time_s": stored["time_s"],
                     **image_error(reference, reference)}
    rows = []
    bundled = scene_data(preset, width=width, height=height)
    for knob, settings in knobs(preset).items():
        if knob in knob_names:
            for setting in settings:
                rows.append({"scene": name, "knob": knob, "setting": setting.label,
                             **measure(bundled, reference, setting, repeat=repeat, seed=seed)})
    for level in (q for q in QUALITY if q != "reference"):
        data = scene_data(preset, width=width, height=height, quality=level)
        rows.append({"scene": name, "knob": "level", "setting": level,
                     **measure(data, reference, Setting(level), repeat=repeat, seed=seed)})
    return rows + [reference_row]


def tolerance_rows(name: str, *, width: int, height: int, repeat: int, seed: int = 0, cache: Path | None = None) -> list[dict]:
    """`march.tolerance` against fixed step counts on a physical report scene, in the tolerance's
    units: the largest radiance error over the brightest light channel and the largest alpha
    (1 − transmittance) error, against the same scene and rays (its spp, shadow steps, ...) with
    only the march made exact (float64, the `reference` level's 2048 steps). Early termination is
    off in every render here: at the levels' 1e-4 it leaves a floor of ~1e-5 of the light that is
    not the march's. Rows (scene, march, tolerance (None for a fixed count), time_s,
    radiance_error, alpha_error, estimate)."""
    preset = SCENES[name]
    bundled = scene_data(preset, width=width, height=height)
    scene = at_level(load_scene(bundled))  # the spp its level gives it
    light = max([c * li.intensity for li in scene.lights for c in li.color] or [1.0])
    # the same scene (its shadow steps, spp, ...) with only the march made exact: float64, the reference's steps
    reference = reference_render(bundled, seed=seed, cache=cache, overrides={
        **NO_EARLY_EXIT, "march.quality": "reference", "march.steps": QUALITY["reference"].steps, "image.spp": scene.image.spp})
    settings = [(f"{n} steps", {"march.steps": n}, None) for n in FIXED_STEPS]
    settings += [(f"tolerance {tol:g}", {"march.tolerance": tol}, tol) for tol in TOLERANCES]
    rows = []
    for label, overrides, tolerance in settings:
        case = load_scene(bundled, {**NO_EARLY_EXIT, **overrides})
        times = []
        for _ in range(repeat):
            start = time.perf_counter()
            out = render(case, seed=seed)
            times.append(time.perf_counter() - start)
        rows.append({"scene": name, "march": label, "tolerance": tolerance, "time_s": statistics.median(times),
                     "radiance_error": float((out.radiance.double() - reference["radiance"].double()).abs().max()) / light,
                     "alpha_error": float((out.alpha.double() - reference["alpha"].double()).abs().max()),
                     "estimate": out.stats.get("error_estimate")})
    return rows


def tolerance_table(rows: Sequence[dict]) -> str:
    """The tolerance rows as a Markdown table, then per tolerance whether it held and what the
    cheapest fixed step count with errors as small took."""
    lines = ["| scene | march | time (s) | max radiance error / light | max alpha error | estimate in `stats` |",
             "| --- | --- | ---: | ---: | ---: | ---: |"]
    for r in rows:
        estimate = "" if r["estimate"] is None else f"{r['estimate']:.1e}"
        lines.append(f"| {r['scene']} | {r['march']} | {r['time_s']:.3f} | {r['radiance_error']:.1e} | {r['alpha_error']:.1e} | {estimate} |")
    lines.append("")
    for r in (r for r in rows if r["tolerance"] is not None):
        held = "holds" if max(r["radiance_error"], r["alpha_error"]) <= r["tolerance"] else "does NOT hold"
        fixed = [f for f in rows if f["scene"] == r["scene"] and f["tolerance"] is None
                 and f["radiance_error"] <= r["radiance_error"] and f["alpha_error"] <= r["alpha_error"]]
        if fixed:
            best = min(fixed, key=lambda f: f["time_s"])
            versus = (f"the cheapest fixed count as accurate, {best['march']}, takes {best['time_s']:.3f} s "
                      f"(the tolerance march takes {r['time_s'] / best['time_s']:.2f}× that)")
        else:
            versus = f"no fixed count up to {FIXED_STEPS[-1]} steps is as accurate"
        lines.append(f"- {r['scene']}, {r['march']}: the tolerance {held}; {r['time_s']:.3f} s, where {versus}.")
    return "\n".join(lines) + "\n"


def table(rows: Sequence[dict]) -> str:
    """The rows as a Markdown table."""
    lines = ["| scene | knob | setting | time (s) | rel. RMSE | PSNR (dB) |", "| --- | --- | --- | ---: | ---: | ---: |"]
    for r in rows:
        psnr = "∞" if math.isinf(r["psnr"]) else f"{r['psnr']:.1f}"
        lines.append(f"| {r['scene']} | {r['knob']} | {r['setting']} | {r['time_s']:.3f} | {r['rel_rmse']:.2e} | {psnr} |")
    return "\n".join(lines) + "\n"


def plot(rows: Sequence[dict], path: Path) -> None:
    """Relative RMSE against time (log-log), one panel per scene, one curve per knob, levels labelled."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(r["scene"] for r in rows))
    fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 3.4), squeeze=False)
    floor = min((r["rel_rmse"] for r in rows if r["rel_rmse"] > 0), default=1e-6) / 2  # exact renders: plottable on log axes
    for ax, name in zip(axes[0], names):
        for knob in dict.fromkeys(r["knob"] for r in rows if r["scene"] == name):
            pts = [r for r in rows if r["scene"] == name and r["knob"] == knob]
            xs, ys = [r["time_s"] for r in pts], [max(r["rel_rmse"], floor) for r in pts]
            if knob == "level":
                ax.plot(xs, ys, "k*--", label="quality level", markersize=9)
                for r, x, y in zip(pts, xs, ys):
                    ax.annotate(r["setting"], (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
            else:
                ax.plot(xs, ys, "o-", label=knob, markersize=3)
        ax.set(xscale="log", yscale="log", title=name, xlabel="time (s)", ylabel="relative RMSE vs reference")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=72)
    plt.close(fig)


def accuracy(out: str | Path, *, width: int = 64, height: int = 36, repeat: int = 3, scenes: Sequence[str] | None = None,
             knob_names: Sequence[str] | None = None, seed: int = 0) -> list[dict]:
    """The accuracy report: writes `out`/accuracy.md and `out`/accuracy.png; returns the rows.
    `scenes`: report scene names or presets (default all of SCENES); `knob_names`: subset of KNOBS."""
    by_preset = {v: k for k, v in SCENES.items()}
    names = []
    for s in scenes if scenes is not None else list(SCENES):
        if s not in SCENES and s not in by_preset:
            fail("--scenes", s, "expected one of " + ", ".join(SCENES.values()) + did_you_mean(s, by_preset))
        names.append(by_preset.get(s, s))
    for k in knob_names if knob_names is not None else ():
        if k not in KNOBS:
            fail("--knobs", k, "expected some of " + ", ".join(KNOBS) + did_you_mean(k, KNOBS))
    for key, value in (("--width", width), ("--height", height), ("--repeat", repeat)):
        if value < 1:
            fail(key, value, "expected an integer >= 1")
    out = Path(out)
    knob_names = KNOBS if knob_names is None else knob_names
    rows = [row for name in names for row in scene_rows(name, width=width, height=height, repeat=repeat, seed=seed,
                                                          knob_names=knob_names, cache=out / "references")]
    text = table(rows)
    if "tolerance" in knob_names:
        tolerance = [row for name in names if is_physical(SCENES[name])
                     for row in tolerance_rows(name, width=width, height=height, repeat=repeat, seed=seed, cache=out / "references")]
        if tolerance:
            text += "\n## Error-controlled marching (`march.tolerance`) against fixed step counts\n\n" + tolerance_table(tolerance)
    out.mkdir(parents=True, exist_ok=True)
    (out / "accuracy.md").write_text(text)
    plot(rows, out / "accuracy.png")
    return rows
