"""`torchvol bench accuracy`: error against time on the bundled scenes, per knob and per quality level.

Each knob is a curve: the scene as bundled with one setting changed (primary steps, integrator,
shadow steps, N accumulated passes of k steps, the air's steps, LOD, spp, the Dr.Jit kernels: `compile`, off being the
eager reference every other row renders). Each quality level is one row: the scene with every key the
level decides removed (`reference.at_quality`). Every row of a scene is measured against one
reference, the same as `torchvol sweep`'s (`reference.Ladder`, at the rows' largest spp with the
same seeded sub-samples), climbed until its own bound is `factor` times under the smallest error of
the scene's rows (or under its floor): relative RMSE and PSNR, with the reference's bound beside
them. Time is the median wall time of `repeat` renders (a render's first call in kernels, which
builds them, is not counted). Writes DIR/accuracy.md (Markdown tables) and DIR/accuracy.png (error
against time, one panel per scene). For physical scenes the `tolerance` knob adds a table of
`march.tolerance` against fixed step counts in the tolerance's own units (radiance over the light,
alpha), against the same scene and rays with only the march made exact, with whether each tolerance
held and what the cheapest as-accurate fixed count took. References are cached in DIR/references/
(or `cache`), keyed by a hash of the reference scene: a re-run (another knob, more repeats) reuses
them instead of rendering the slowest part of the report again. Every report ends with what each
technique preset (`TECHNIQUES`) costs as bundled, per pass, and with voxel GI's accuracy-for-time
trade (`cone_rows`: cone tracing and path tracing, with and without distance LOD, against many paths);
`--scenes` takes those presets too, for their error curves.
"""

from __future__ import annotations

import math
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import torch

from ..fields import DENSITIES
from ..renderer.executor import render
from ..runtime.progress import progress as bar
from ..scene.model import load_scene
from ..scene.presets import preset_dict
from ..scene.quality import QUALITY, Quality, at_level
from ..schema.validate import did_you_mean, fail, finite, integer
from ..volume.shading import SHADINGS
from .reference import (
    EVERY_ORDER_FACTOR,
    PATH_BOUNCES,
    PATH_PATHS,
    Ladder,
    at_quality,
    cached_render,
    every_order_applies,
    image_error,
    with_every_order,
)

# report name -> bundled preset: the scenes of a default report
SCENES = {"template clouds": "template-clouds", "physical clouds": "cloud-puff", "voxel terrain": "voxel-terrain"}
# the variants' techniques (docs/VOLUMES.md): every report states their cost (`cost_rows`); `--scenes NAME`
# measures any of them like the scenes above, against its own reference
TECHNIQUES = ("explosion", "fire", "atmosphere", "cloudscape", "fur-ball", "terrain-clouds", "multi-layer", "particles",
              "god-rays")
# the tolerance table: error-controlled marching against fixed step counts
TOLERANCES = (1e-2, 1e-3, 1e-4)
FIXED_STEPS = (32, 48, 64, 96, 128, 160, 192, 256, 384, 512, 768)  # fine enough that "as accurate" is a fair match
NO_EARLY_EXIT = {"march.min_transmittance": 1e-12}  # early termination leaves an error floor of its own
EXACT_MARCH_STEPS = 2048  # the tolerance table's reference march (float64); its bound: against half as many
LONG_RENDER_S = 10.0
# accumulation against one march at equal time: N passes of k steps beside the `steps` knob's N·k
ACCUMULATE = ((4, 16), (4, 32), (16, 16))


@dataclass(frozen=True)
class Setting:
    """One point of a knob's curve: scene key overrides ({key path: value}) and the compile flag."""

    label: str
    overrides: dict[str, Any] = field(default_factory=dict)
    compile: bool = False


def _values(key: str, values: Sequence[Any]) -> list[Setting]:
    return [Setting(f"{value}", {key: value}) for value in values]


def is_physical(preset: str) -> bool:
    """Whether the tolerance table applies: the physically shaded report scene."""
    return preset == "cloud-puff"


def knobs(preset: str) -> dict[str, list[Setting]]:
    """The knobs that apply to `preset`, each a list of settings over the scene as bundled, read
    from what the scene holds (volumes, their shading and densities, shadows, voxels, air)."""
    scene = load_scene(preset_dict(preset))
    physical = [v for v in scene.volumes if SHADINGS[v.shading].caps["physical"]]
    out: dict[str, list[Setting]] = {}
    if scene.volumes:
        out["steps"] = _values("march.steps", [16, 32, 64, 128, 256])
    if physical:  # the alpha looks' integrator is their look, not an approximation
        out["integrator"] = _values("march.integrator", ["alpha", "riemann", "frostbite"])
        if scene.lights and scene.lights[0].shadow is not None:
            out["shadow_steps"] = _values("lights[0].shadow.steps", [2, 4, 8, 16, 32])
        if is_physical(preset):
            out["passes"] = [Setting(f"{n} × {k} steps", {"image.passes": n, "march.steps": k}) for n, k in ACCUMULATE]
    if scene.voxels is not None and scene.voxels.shadow is not None:
        out["shadow_steps"] = _values("voxels.shadow.steps", [8, 16, 32, 64, 128])
    if scene.atmosphere is not None:
        out["air_steps"] = [Setting(f"{n}/{n // 2}", {"atmosphere.steps": n, "atmosphere.light_steps": n // 2}) for n in (4, 8, 16, 32)]
    if any(DENSITIES[v.density.kind].caps.get("octaves") for v in scene.volumes):
        out["lod"] = [Setting("off", {"march.lod": None}), Setting("on", {"march.lod": {"scale": 0.5}})]
    out["spp"] = _values("image.spp", [1, 2, 4])
    out["compile"] = [Setting("off"), Setting("on", compile=True)]
    return out


# the curves of the main table, and `tolerance`: a table of its own, in the tolerance's units (`tolerance_rows`)
KNOBS = ("steps", "integrator", "shadow_steps", "passes", "air_steps", "lod", "spp", "compile", "tolerance")


def scene_data(preset: str, *, width: int, height: int, quality: Quality | None = None) -> dict:
    """The preset's scene dict at `width`×`height`; at `quality` (the level's keys removed) if given."""
    data = preset_dict(preset, width=width, height=height)
    return data if quality is None else at_quality(data, quality)


def measure(data: dict, setting: Setting, *, repeat: int, seed: int = 0):
    """(median wall time, the last RenderOutput) of `repeat` renders of `data` with `setting`; a
    render that takes over LONG_RENDER_S is timed once (its timing noise is small against it)."""
    scene = load_scene(data, setting.overrides)
    if setting.compile:
        render(scene, seed=seed, compile=True)  # the kernels' build is not what is measured
    times = []
    while len(times) < repeat and sum(times) < LONG_RENDER_S:
        start = time.perf_counter()
        out = render(scene, seed=seed, compile=setting.compile)
        times.append(time.perf_counter() - start)
    return statistics.median(times), out


def scene_rows(name: str, *, width: int, height: int, repeat: int, knob_names: Sequence[str], seed: int = 0,
               cache: Path | None = None, factor: float = 10.0, shown=None) -> tuple[list[dict], dict]:
    """Rows (scene, knob, setting, time_s, rmse, rel_rmse, psnr, bound, rel_bound) of one report
    scene, every applicable knob in `knob_names` then one row per quality level, and the reference
    they are measured against ({"rung", "tolerance", "dtype", "time_s", "bound"}). `shown`: a
    progress bar, advanced by one per row."""
    preset = SCENES.get(name, name)
    bundled = scene_data(preset, width=width, height=height)
    cases = [(knob, s.label, bundled, s) for knob, settings in knobs(preset).items() if knob in knob_names for s in settings]
    cases += [("level", level, scene_data(preset, width=width, height=height, quality=level), Setting(level)) for level in QUALITY]
    measured = []
    for knob, label, data, setting in cases:
        if shown is not None:
            shown.set_postfix_str(f"{name}: {knob} {label}")
        time_s, out = measure(data, setting, repeat=repeat, seed=seed)
        measured.append((time_s, out.image))
        if shown is not None:
            shown.update(1)
    spp = max(at_level(load_scene(data, s.overrides)).image.spp for _, _, data, s in cases)
    on_render = None if shown is None else (lambda k, tol: shown.set_postfix_str(f"{name}: reference rung {k}, tolerance {tol:.1e}"))
    ladder = Ladder(bundled, seed=seed, spp=spp, cache=cache, on_render=on_render)
    ref = ladder.settle([image for _, image in measured], factor=factor)
    rms = image_error(torch.zeros_like(ref.image), ref.image)["rmse"]
    truth = None
    if every_order_applies(bundled):  # octaves: also against every order of scattering, path-traced
        on_path = None if shown is None else (lambda k, tol: shown.set_postfix_str(f"{name}: every-order reference rung {k}"))
        truth = Ladder(with_every_order(bundled), seed=seed, spp=spp, cache=cache, on_render=on_path).settle(
            [image for _, image in measured], factor=EVERY_ORDER_FACTOR)
    rows = [{"scene": name, "knob": knob, "setting": label, "time_s": time_s, **image_error(image, ref.image),
             "bound": ref.bound, "rel_bound": ref.bound / rms if rms > 0 else math.inf,
             "every_order_rel_rmse": None if truth is None else truth.error_against(image)["rel_rmse"]}
            for (knob, label, _, _), (time_s, image) in zip(cases, measured)]
    every = None if truth is None else {"rung": truth.rung, "time_s": truth.time_s, "bound": truth.bound,
                                        "rel_bound": truth.bound / image_error(torch.zeros_like(truth.image), truth.image)["rmse"]}
    return rows, {"scene": name, "rung": ref.rung, "tolerance": ref.tolerance, "dtype": ref.dtype, "time_s": ref.time_s,
                  "bound": ref.bound, "spp": spp, "every_order": every}


def tolerance_rows(name: str, *, width: int, height: int, repeat: int, seed: int = 0, cache: Path | None = None,
                   shown=None) -> list[dict]:
    """`march.tolerance` against fixed step counts on a physical report scene, in the tolerance's
    units: the largest radiance error over the brightest light channel and the largest alpha
    (1 − transmittance) error, against the same scene and rays (its spp, shadow steps, ...) with
    only the march made exact (float64, EXACT_MARCH_STEPS steps; its bound, in the same units, is
    how far it moves from half as many steps). Early termination is off in every render here: at
    the levels' 1e-4 it leaves a floor of ~1e-5 of the light that is not the march's. Rows (scene,
    march, tolerance (None for a fixed count), time_s, radiance_error, alpha_error, estimate,
    radiance_bound, alpha_bound)."""
    preset = SCENES.get(name, name)
    bundled = scene_data(preset, width=width, height=height)
    scene = at_level(load_scene(bundled))  # the spp its level gives it
    light = max([c * li.intensity for li in scene.lights for c in li.color] or [1.0])

    def exact(steps: int) -> dict:  # the same scene, rays and shadows with only the march made exact
        if shown is not None:
            shown.set_postfix_str(f"{name}: exact march, {steps} steps")
        return cached_render(load_scene(bundled, {**NO_EARLY_EXIT, "march.quality": "reference", "march.steps": steps,
                                                  "image.spp": scene.image.spp}).model_dump(), seed=seed, dtype=None, cache=cache)

    reference, coarse = exact(EXACT_MARCH_STEPS), exact(EXACT_MARCH_STEPS // 2)

    def errors(radiance: torch.Tensor, alpha: torch.Tensor) -> tuple[float, float]:
        return (float((radiance.double() - reference["radiance"].double()).abs().max()) / light,
                float((alpha.double() - reference["alpha"].double()).abs().max()))

    radiance_bound, alpha_bound = errors(coarse["radiance"], coarse["alpha"])
    settings = [(f"{n} steps", {"march.steps": n}, None) for n in FIXED_STEPS]
    settings += [(f"tolerance {tol:g}", {"march.tolerance": tol}, tol) for tol in TOLERANCES]
    rows = []
    for label, overrides, tolerance in settings:
        if shown is not None:
            shown.set_postfix_str(f"{name}: {label}")
        time_s, out = measure(bundled, Setting(label, {**NO_EARLY_EXIT, **overrides}), repeat=repeat, seed=seed)
        radiance_error, alpha_error = errors(out.radiance, out.alpha)
        rows.append({"scene": name, "march": label, "tolerance": tolerance, "time_s": time_s,
                     "radiance_error": radiance_error, "alpha_error": alpha_error, "estimate": out.stats.get("error_estimate"),
                     "radiance_bound": radiance_bound, "alpha_bound": alpha_bound})
        if shown is not None:
            shown.update(1)
    return rows


def tolerance_table(rows: Sequence[dict]) -> str:
    """The tolerance rows as a Markdown table, then per tolerance whether it held and what the
    cheapest fixed step count with errors as small took."""
    lines = ["| scene | march | time (s) | max radiance error / light ± reference bound | max alpha error ± reference bound "
             "| estimate in `stats` |", "| --- | --- | ---: | ---: | ---: | ---: |"]
    for r in rows:
        estimate = "" if r["estimate"] is None else f"{r['estimate']:.1e}"
        lines.append(f"| {r['scene']} | {r['march']} | {r['time_s']:.3f} | {r['radiance_error']:.1e} ± {r['radiance_bound']:.0e} "
                     f"| {r['alpha_error']:.1e} ± {r['alpha_bound']:.0e} | {estimate} |")
    lines.append("")
    for r in {r["scene"]: r for r in rows}.values():
        lines.append(f"- {r['scene']}: the reference is a float64 march of {EXACT_MARCH_STEPS} steps; its bound is how far it "
                     f"moves from {EXACT_MARCH_STEPS // 2} steps ({r['radiance_bound']:.1e} of the light, {r['alpha_bound']:.1e} in alpha).")
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


def table(rows: Sequence[dict], references: Sequence[dict]) -> str:
    """The rows as a Markdown table, then a line per scene on the reference they were measured against."""
    lines = ["| scene | knob | setting | time (s) | rel. RMSE | ± reference bound | PSNR (dB) | rel. RMSE against every order |",
             "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        psnr = "∞" if math.isinf(r["psnr"]) else f"{r['psnr']:.1f}"
        every = "" if r.get("every_order_rel_rmse") is None else f"{r['every_order_rel_rmse']:.2e}"
        lines.append(f"| {r['scene']} | {r['knob']} | {r['setting']} | {r['time_s']:.3f} | {r['rel_rmse']:.2e} | "
                     f"{r['rel_bound']:.0e} | {psnr} | {every} |")
    lines.append("")
    for ref in references:
        smallest = min(r["rmse"] for r in rows if r["scene"] == ref["scene"])
        under = smallest / ref["bound"] if ref["bound"] > 0 else math.inf
        lines.append(f"- {ref['scene']}: reference rung {ref['rung']} (tolerance {ref['tolerance']:.2g}, {ref['dtype']}, "
                     f"{ref['spp']} spp), {ref['time_s']:.1f} s to render; its bound (RMSE {ref['bound']:.1e}) is "
                     f"{under:.3g}× under the smallest error of its rows.")
        every = ref.get("every_order")
        if every is not None:
            lines.append(f"- {ref['scene']}, every order of scattering: path-traced (`[path]`, "
                         f"{PATH_BOUNCES} scatterings a path), rung {every['rung']} ({PATH_PATHS * 4 ** (every['rung'] - 1)} "
                         f"paths a pixel), {every['time_s']:.1f} s to render; its noise bound: {every['rel_bound']:.1e} "
                         "relative RMSE (what single scattering and the octaves leave out is the last column).")
    return "\n".join(lines) + "\n"


def cost_rows(presets: Sequence[str], *, width: int, height: int, repeat: int, seed: int = 0, shown=None) -> list[dict]:
    """What each technique costs as bundled: rows (preset, time_s (median of `repeat`), passes {pass:
    seconds} of the last render, density_evals)."""
    rows = []
    for preset in presets:
        if shown is not None:
            shown.set_postfix_str(f"cost: {preset}")
        time_s, out = measure(scene_data(preset, width=width, height=height), Setting("bundled"), repeat=repeat, seed=seed)
        rows.append({"preset": preset, "time_s": time_s, "passes": out.stats["time_s"], "density_evals": out.stats["density_evals"]})
        if shown is not None:
            shown.update(1)
    return rows


def cost_table(rows: Sequence[dict], *, width: int, height: int) -> str:
    """The cost rows as a Markdown table: total time and the passes that took over 1% of it."""
    lines = [f"| preset | time (s) at {width}×{height} | density samples | passes (s) |", "| --- | ---: | ---: | --- |"]
    for r in rows:
        passes = ", ".join(f"{name} {s:.3f}" for name, s in r["passes"].items() if s >= 0.01 * r["time_s"])
        lines.append(f"| {r['preset']} | {r['time_s']:.3f} | {r['density_evals']:,} | {passes} |")
    return "\n".join(lines) + "\n"


# cone tracing against path tracing (`cone_rows`): the voxel-cone preset without its tonemap and cone AO
# (the path tracer has none), one bounce; each row (method, its voxels.gi, its label) against REF_PATHS paths
CONE_PRESET, REF_PATHS, CONE_LOD = "voxel-cone", 256, {"near": 12.0, "far": 24.0}
CONE_SETTINGS = (
    [("path", {"method": "path", "bounces": 1, "samples": n}, f"{n} paths") for n in (4, 16, 64)]
    + [("path", {"method": "path", "bounces": 1, "samples": 16, "lod": {**CONE_LOD, "samples": 4}}, "16 paths, LOD (4 far)")]
    + [("cone", {"method": "cone", "cones": n}, f"{n} cones") for n in (1, 3, 6, 16)]
    + [("cone", {"method": "cone", "cones": 6, "lod": {**CONE_LOD, "cones": 3, "aperture": 50.0}}, "6 cones, LOD (3 far)")])


def cone_rows(*, width: int, height: int, repeat: int, seed: int = 0, shown=None) -> list[dict]:
    """Cone-traced against path-traced GI on the voxel-cone preset at `width`×`height`: rows (method,
    setting, time_s (median of `repeat`), rel_rmse of the radiance against a REF_PATHS-path render,
    its time (ref_s) and the rows' own time over it (measured in the same run))."""
    data = scene_data(CONE_PRESET, width=width, height=height)
    data["post"] = {}
    data["voxels"]["gi"] = {"method": "path", "bounces": 1, "samples": REF_PATHS}
    ref_s, ref = measure(data, Setting("reference"), repeat=1, seed=seed)
    rows = []
    for method, gi, label in CONE_SETTINGS:
        if shown is not None:
            shown.set_postfix_str(f"cone: {label}")
        data["voxels"]["gi"] = gi
        time_s, out = measure(data, Setting(label), repeat=repeat, seed=seed)
        rel = image_error(out.radiance, ref.radiance)["rel_rmse"]
        rows.append({"method": method, "setting": label, "time_s": time_s, "rel_rmse": rel, "ref_s": ref_s})
        if shown is not None:
            shown.update(1)
    return rows


def cone_table(rows: Sequence[dict], *, width: int, height: int) -> str:
    """The GI cone comparison as a Markdown table: a row per (method, setting) of `rows`, its time
    against the path-traced reference's and its relative RMSE, at `width`×`height`."""
    lines = [f"| GI | setting | time (s) at {width}×{height} | × reference time | rel. RMSE vs {REF_PATHS} paths |",
             "| --- | --- | ---: | ---: | ---: |"]
    for r in rows:
        lines.append(f"| {r['method']} | {r['setting']} | {r['time_s']:.3f} | {r['time_s'] / r['ref_s']:.3f} | {r['rel_rmse']:.2%} |")
    return "\n".join(lines) + f"\n\nReference: {REF_PATHS} paths (one bounce), {rows[0]['ref_s']:.2f} s.\n"


def plot(rows: Sequence[dict], path: Path) -> None:
    """Relative RMSE against time (log-log), one panel per scene, one curve per knob, levels
    labelled; each error's bar is the reference's bound."""
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
            bounds = [min(r["rel_bound"], y - floor / 2) for r, y in zip(pts, ys)]  # bars stay above 0 on log axes
            if knob == "level":
                ax.errorbar(xs, ys, yerr=bounds, fmt="k*--", label="quality level", markersize=9)
                for r, x, y in zip(pts, xs, ys):
                    ax.annotate(r["setting"], (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
            else:
                ax.errorbar(xs, ys, yerr=bounds, fmt="o-", label=knob, markersize=3)
        ax.set(xscale="log", yscale="log", title=name, xlabel="time (s)", ylabel="relative RMSE vs reference")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=72)
    plt.close(fig)


def accuracy(out: str | Path, *, width: int = 64, height: int = 36, repeat: int = 3, scenes: Sequence[str] | None = None,
             knob_names: Sequence[str] | None = None, seed: int = 0, factor: float = 10.0, cache: str | Path | None = None,
             progress: bool | None = None) -> list[dict]:
    """The accuracy report: writes `out`/accuracy.md and `out`/accuracy.png; returns the rows.
    `scenes`: report scene names or presets (default all of SCENES); `knob_names`: subset of KNOBS;
    `factor`: how far under the smallest error of a scene's rows its reference's bound must be;
    `cache`: the references' folder (default `out`/references); `progress`: a bar on stderr (None:
    on a terminal only)."""
    by_preset = {v: k for k, v in SCENES.items()}
    names = []
    for s in scenes if scenes is not None else list(SCENES):
        if s not in SCENES and s not in by_preset and s not in TECHNIQUES:
            allowed = [*SCENES.values(), *TECHNIQUES]
            fail("scenes", s, "expected some of " + ", ".join(allowed) + did_you_mean(s, allowed))
        names.append(by_preset.get(s, s))
    for k in knob_names if knob_names is not None else ():
        if k not in KNOBS:
            fail("knob_names", k, "expected some of " + ", ".join(KNOBS) + did_you_mean(k, KNOBS))
    for key, value in (("width", width), ("height", height), ("repeat", repeat)):
        integer(key, value, low=1)
    finite("factor", factor, low=1)
    out = Path(out)
    cache = out / "references" if cache is None else Path(cache)
    knob_names = KNOBS if knob_names is None else knob_names
    physical = [n for n in names if is_physical(SCENES.get(n, n))] if "tolerance" in knob_names else []
    total = sum(len([s for k, v in knobs(SCENES.get(n, n)).items() if k in knob_names for s in v]) + len(QUALITY) for n in names)
    total += len(physical) * (len(FIXED_STEPS) + len(TOLERANCES)) + len(TECHNIQUES) + len(CONE_SETTINGS)
    rows, references, tolerance = [], [], []
    with bar(total, desc="bench accuracy", unit="render", enabled=sys.stderr.isatty() if progress is None else progress) as shown:
        for name in names:
            scene, reference = scene_rows(name, width=width, height=height, repeat=repeat, seed=seed, knob_names=knob_names,
                                          cache=cache, factor=factor, shown=shown)
            rows += scene
            references.append(reference)
        for name in physical:
            tolerance += tolerance_rows(name, width=width, height=height, repeat=repeat, seed=seed, cache=cache, shown=shown)
        costs = cost_rows(TECHNIQUES, width=width, height=height, repeat=repeat, seed=seed, shown=shown)
        cones = cone_rows(width=width, height=height, repeat=repeat, seed=seed, shown=shown)
    text = table(rows, references)
    text += "\n## What each technique costs, as bundled\n\n" + cost_table(costs, width=width, height=height)
    if tolerance:
        text += "\n## Error-controlled marching (`march.tolerance`) against fixed step counts\n\n" + tolerance_table(tolerance)
    text += ("\n## Voxel GI: cone tracing against path tracing (voxel-cone, one bounce)\n\n"
             + cone_table(cones, width=width, height=height))
    out.mkdir(parents=True, exist_ok=True)
    (out / "accuracy.md").write_text(text)
    plot(rows, out / "accuracy.png")
    return rows
