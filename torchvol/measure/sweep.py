"""`torchvol sweep`: what each setting costs in time and error, on a scene or on a recipe's samples.

Every combination of the swept values (`params`: {key path: [values]}) is a setting; `levels` adds
the named quality levels, each deciding every approximation itself (`at_quality`), and so does a
swept `march.quality`. A setting renders each sample once (a scene is one sample; a recipe gives
samples 0..N−1, the same draws for every setting) and is measured against a reference of that
sample (`torchvol.measure.reference`): the converged image, refined until its own error bound is `factor`
times under the setting's error. Swept keys that only set an approximation (`is_approximation`:
march keys, spp, shadow steps, step limits) share their sample's reference; other swept keys
(σ_t, ...) change the scene and get references of their own.

Writes to DIR, as it goes (an interrupted sweep keeps what it measured; a re-run resumes):
  sweep.json         what is swept; a re-run into DIR must sweep the same (else it is refused)
  results.csv        a row per setting and sample, appended as measured: time, density evaluations,
                     RMSE, relative RMSE and PSNR against the reference, and the reference's own
                     bound (in RMSE), rung, tolerance and dtype; where the scene gets one
                     (`every_order`), RMSE and relative RMSE against its every-order reference
                     (path-traced, `reference.with_every_order`: what single scattering and
                     the octaves leave out), that reference's bound and rung
  images/            each setting's render of sample 0 (float32 .npy), for the figures
  references/        the reference rungs (a cache keyed by a hash of each rung's scene)
and at the end:
  summary.csv        per setting: samples, mean and spread of time and error, worst error and bound
  pareto.png, contact_sheet.png, difference.png, plot_<key>.png (`torchvol.measure.figures`)
"""

from __future__ import annotations

import copy
import csv
import itertools
import json
import math
import re
import statistics
import sys
from pathlib import Path
from typing import Any, Literal, Mapping, Sequence

import numpy as np
import torch

from ..dataset.recipe import Recipe, render_seed
from ..runtime.progress import progress as bar
from ..scene.model import load_scene
from ..scene.quality import QUALITY, at_level
from ..schema.keypath import path_str, set_path
from ..schema.validate import fail, finite, integer
from ..version import __version__
from . import figures
from .reference import (
    EVERY_ORDER_FACTOR,
    EVERY_ORDER_MODES,
    Ladder,
    at_quality,
    every_order_applies,
    image_error,
    with_every_order,
)

EveryOrder = Literal["auto", "always", "never"]
QUANTISATION_RMSE = 1.0 / (255.0 * math.sqrt(12.0))  # 8-bit rounding's RMSE: smaller errors vanish in a stored PNG
MEASURED = ("time_s", "density_evals", "rmse", "rel_rmse", "psnr", "reference_bound", "reference_rung",
            "reference_tolerance", "reference_dtype")
EVERY_ORDER = ("every_order_rmse", "every_order_rel_rmse", "every_order_bound", "every_order_rung")  # blank: none
_APPROXIMATION = re.compile(
    r"march\.(?!max_distance$).+|image\.spp|lights\[\d+\]\.shadow\.(steps|growth|first_step|method|resolution)"
    r"|voxels\.(max_steps|traversal|shadow\.steps|fog\.shadow_steps)|(sky\.)?atmosphere\.(steps|light_steps)|path\.samples")


def split_values(text: str) -> list[str]:
    """'8,16,[1,2,3]' -> ['8', '16', '[1,2,3]']: commas inside brackets/braces/quotes do not split."""
    parts, depth, quote, current = [], 0, None, ""
    for ch in text:
        if quote:
            quote = None if ch == quote else quote
        elif ch in "\"'":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            parts.append(current.strip())
            current = ""
            continue
        current += ch
    parts.append(current.strip())
    return [p for p in parts if p]


def key_path(key: str) -> str:
    """A key path in one spelling: 'volumes.0.sigma_t' and 'volumes[0].sigma_t' -> 'volumes[0].sigma_t'."""
    parts = [p for p in key.replace("[", ".").replace("]", "").split(".") if p]
    return path_str(tuple(int(p) if p.isdigit() else p for p in parts))


def is_approximation(key: str) -> bool:
    """Whether a key only sets how accurately a scene is rendered (its reference decides it) rather
    than what the scene is: march keys but `max_distance`, `image.spp`, the lights' shadow march,
    voxel step limits and traversal, atmosphere steps."""
    return _APPROXIMATION.fullmatch(key_path(key)) is not None


def settings_of(params: Mapping[str, Sequence[Any]], levels: Sequence[str]) -> list[dict[str, Any]]:
    """Every combination of `params`, then each level in `levels` with every combination of the
    swept scene keys ({"march.quality": level, ...}); no setting twice."""
    keys = list(params)
    out = [dict(zip(keys, combo)) for combo in itertools.product(*params.values())]
    scene_keys = [k for k in keys if not is_approximation(k)]
    for level in levels:
        out += [{"march.quality": level, **dict(zip(scene_keys, combo))}
                for combo in itertools.product(*(params[k] for k in scene_keys))]
    unique: dict[str, dict] = {}
    for values in out:
        unique.setdefault(repr(sorted(values.items(), key=lambda kv: kv[0])), values)
    return list(unique.values())


def setting_data(sample: Mapping, values: Mapping[str, Any]) -> dict:
    """Scene dict of one setting on one sample: at its level first when it names one
    (`march.quality`: the level then decides every approximation key not swept), then its values."""
    data = copy.deepcopy(dict(sample))
    if "march.quality" in values:
        data = at_quality(data, values["march.quality"])
    for key, value in values.items():
        if key != "march.quality":
            set_path(data, key, value)
    return data


def sample_data(recipe: Recipe, index: int, seed: int) -> dict:
    """Sample `index` of `recipe` as a scene dict (the template with the values drawn)."""
    data = copy.deepcopy(recipe.template)
    for path, value in recipe.sample_params(index, seed).items():
        set_path(data, path, value)
    return data


def _cell(value: Any) -> Any:
    return value if isinstance(value, (int, float, str)) else repr(value)


def _text(value: Any) -> str:
    return str(_cell(value))


def label(values: Mapping[str, Any]) -> str:
    """A setting as text: "key=value, ..." in the order of `values`."""
    return ", ".join(f"{k}={_text(v)}" for k, v in values.items())


def _check(params: Mapping, samples: int | None, levels: Sequence[str], factor: float, max_error: float) -> None:
    if not params and not levels:
        fail("params", params, "give at least one key and its values to sweep (or quality levels)")
    for key, values in params.items():
        if not isinstance(values, (list, tuple)) or not values:
            fail(f"params.{key}", values, "expected a non-empty list of values")
    if samples is not None:
        integer("samples", samples, low=1)
    for level in levels:
        if level not in QUALITY:
            fail("levels", level, "expected some of " + ", ".join(QUALITY))
    finite("factor", factor, low=1, why="how far under each error the reference's bound must be")
    finite("max_error", max_error, above=0, why="an RMSE of the display-referred image")


def _resume(out: Path, meta: dict, columns: list[str]) -> dict[tuple, dict]:
    """The rows an earlier run of the same sweep measured, by (sample, values); writes sweep.json."""
    meta_text = json.dumps(meta, sort_keys=True, indent=1, default=repr) + "\n"
    results = out / "results.csv"
    if (out / "sweep.json").is_file():
        if (out / "sweep.json").read_text() != meta_text:
            fail("out", str(out), "holds a sweep of other settings (source, values, seed, samples, levels or "
                 "factor); use a new folder")
    elif results.exists():
        fail("out", str(out), "holds a results.csv of no sweep this version knows; use a new folder")
    out.mkdir(parents=True, exist_ok=True)
    (out / "sweep.json").write_text(meta_text)
    if not results.is_file():
        return {}
    with open(results, newline="") as f:
        rows = [r for r in csv.DictReader(f) if all(r.get(c) not in (None, "") for c in MEASURED) and None not in r.values()]
    if rows and list(rows[0]) != columns:
        fail("out", str(out), "holds a results.csv with other columns; use a new folder")
    partial = results.with_suffix(".partial")
    with open(partial, "w", newline="") as f:  # without a line a kill may have cut short
        writer = csv.DictWriter(f, fieldnames=columns)
        writer.writeheader()
        writer.writerows(rows)
    partial.replace(results)
    for r in rows:
        for c in ("time_s", "rmse", "rel_rmse", "psnr", "reference_bound", "reference_tolerance"):
            r[c] = float(r[c])
        r["density_evals"], r["reference_rung"], r["sample"] = int(r["density_evals"]), int(r["reference_rung"]), int(r["sample"])
        for c in EVERY_ORDER:
            r[c] = "" if r[c] == "" else (int(r[c]) if c == "every_order_rung" else float(r[c]))
    return {(r["sample"], tuple(r[k] for k in columns[1:len(columns) - len(MEASURED) - len(EVERY_ORDER)])): r for r in rows}


def _append(path: Path, row: Mapping, columns: list[str]) -> None:
    new = not path.is_file() or path.stat().st_size == 0
    with open(path, "a", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns)
        if new:
            writer.writeheader()
        writer.writerow(row)


def sweep(source: Any, params: Mapping[str, Sequence[Any]], *, out: str | Path, seed: int = 0,
          overrides: Mapping[str, Any] | None = None, samples: int | None = None, levels: Sequence[str] = (),
          factor: float = 10.0, max_error: float = QUANTISATION_RMSE, cache: str | Path | None = None,
          progress: bool | None = None, every_order: EveryOrder = "auto") -> dict:
    """Sweep `params` ({key path: [values]}) over `source` (a scene, preset name or recipe, plus
    `overrides`); `samples`: draw that many samples of a recipe (required where it draws values).
    `factor`: how far under each error the reference's bound must be; `max_error`: the RMSE the
    verdict's setting must stay within (default: 8-bit quantisation's). `cache`: the reference
    rungs' folder (default DIR/references). `progress`: a bar on stderr (None: on a terminal only).
    `every_order`: which scenes are also measured against a path-traced reference with every order
    of scattering (`reference.every_order_applies`: "auto", those with multiple-scattering octaves).
    Returns {"rows", "summary", "verdict", "written"}; see the module docstring for the files."""
    levels = list(levels)
    _check(params, samples, levels, factor, max_error)
    if every_order not in EVERY_ORDER_MODES:
        fail("every_order", every_order, "expected one of " + ", ".join(EVERY_ORDER_MODES))
    recipe = Recipe.load(source, overrides)
    if recipe.dists and samples is None:
        fail("samples", None, "the source draws values from distributions (a recipe): give the number of samples to draw")
    settings = settings_of(params, levels)
    count = 1 if samples is None else samples
    first = sample_data(recipe, 0, seed)
    for values in settings:  # every setting validated, with its key paths, before any rendering
        load_scene(setting_data(first, values))
    keys = list(params) + (["march.quality"] if levels and "march.quality" not in params else [])
    columns = ["sample", *keys, *MEASURED, *EVERY_ORDER]
    out = Path(out)
    meta = {"format": "torchvol-sweep", "version": __version__, "source": recipe.describe(), "params": dict(params),
            "levels": levels, "seed": seed, "samples": samples, "factor": factor, "every_order": every_order}
    done = _resume(out, meta, columns)
    cache = out / "references" if cache is None else Path(cache)
    (out / "images").mkdir(exist_ok=True)
    groups: dict[str, list[dict]] = {}  # settings by their swept scene values: one reference each
    for values in settings:
        groups.setdefault(repr({k: v for k, v in values.items() if not is_approximation(k)}), []).append(values)
    rows = _measure_all(recipe, settings, groups, keys, columns, done, first=first, count=count, seed=seed,
                        samples=samples, out=out, cache=cache, factor=factor, progress=progress, every_order=every_order)
    ordered = [rows[_row_key(keys, i, v)] for i in range(count) for v in settings]
    summary = summarise(ordered, settings, keys)
    _write_csv(out / "summary.csv", summary)
    verdict_text = verdict(summary, keys, max_error=max_error)
    written = [out / "results.csv", out / "summary.csv"]
    written += _figures(out, settings, keys, summary, ordered, groups, first, seed if samples is None else render_seed(0, seed),
                        cache, max_error)
    return {"rows": ordered, "summary": summary, "verdict": verdict_text, "written": [str(p) for p in written]}


def _row_key(keys: Sequence[str], index: int, values: Mapping) -> tuple:
    """A results row's key: (sample, the swept values as text, "" for a key the setting lacks)."""
    return index, tuple(_text(values[k]) if k in values else "" for k in keys)


def _measure_all(recipe: Recipe, settings: list[dict], groups: dict[str, list[dict]], keys: list[str], columns: list[str],
                 done: dict[tuple, dict], *, first: dict, count: int, seed: int, samples: int | None, out: Path,
                 cache: Path, factor: float, progress: bool | None, every_order: EveryOrder) -> dict[tuple, dict]:
    """Renders each of `count` samples at every setting not `done`, against one reference ladder
    per group of `groups` (and one every-order ladder where `every_order` gives it one), appending each row to results.csv (sample 0's images to images/).
    -> every row, `done`'s too, by `_row_key`."""
    from ..renderer.executor import render

    rows = dict(done)
    enabled = sys.stderr.isatty() if progress is None else progress
    with bar(len(settings) * count, initial=len(done), desc="sweep", unit="render", enabled=enabled) as shown:
        warmed = False
        for index in range(count):
            data = sample_data(recipe, index, seed) if index else first
            seed_of_sample = seed if samples is None else render_seed(index, seed)
            for group in groups.values():
                todo = [v for v in group if _row_key(keys, index, v) not in done]
                if not todo:
                    continue
                scene_values = {k: v for k, v in group[0].items() if not is_approximation(k)}
                spp = max(at_level(load_scene(setting_data(data, v))).image.spp for v in group)
                scene_data = setting_data(data, scene_values)
                ladder = Ladder(scene_data, seed=seed_of_sample, spp=spp, cache=cache,
                                on_render=lambda k, tol: shown.set_postfix_str(f"sample {index}: reference rung {k}, tolerance {tol:.1e}"))
                every = (Ladder(with_every_order(scene_data), seed=seed_of_sample, spp=spp, cache=cache,
                                on_render=lambda k, tol: shown.set_postfix_str(f"sample {index}: every-order reference rung {k}"))
                         if every_order_applies(scene_data, every_order) else None)
                for values in todo:
                    scene = load_scene(setting_data(data, values))
                    if not warmed:  # a first render pays one-off costs (allocator, threads): not the setting's
                        render(load_scene(scene.model_dump(), {"image.width": 8, "image.height": 8}), seed=seed_of_sample)
                        warmed = True
                    shown.set_postfix_str(f"sample {index}: {label(values)}")
                    row, image = _measure(scene, values, index, keys, seed=seed_of_sample, ladders=(ladder, every),
                                          factor=factor)
                    if index == 0:
                        np.save(out / "images" / f"{settings.index(values):03d}.npy", image.numpy())
                    _append(out / "results.csv", row, columns)
                    rows[_row_key(keys, index, values)] = row
                    shown.update(1)
    return rows


def _measure(scene, values: Mapping, index: int, keys: Sequence[str], *, seed: int,
             ladders: tuple[Ladder, Ladder | None], factor: float) -> tuple[dict, torch.Tensor]:
    """Renders `scene` (sample `index` at the setting `values`) and measures it against the
    references of `ladders` (its own; its every-order one or None). -> (its results row, its image
    (3, H, W))."""
    from ..renderer.executor import render

    result = render(scene, seed=seed)
    ref = ladders[0].settle([result.image], factor=factor)
    error = image_error(result.image, ref.image)
    every = dict.fromkeys(EVERY_ORDER, "")
    if ladders[1] is not None:
        truth = ladders[1].settle([result.image], factor=EVERY_ORDER_FACTOR)
        measured = truth.error_against(result.image)
        every = dict(zip(EVERY_ORDER, (measured["rmse"], measured["rel_rmse"], truth.bound, truth.rung)))
    row = {"sample": index, **{k: _cell(values[k]) if k in values else "" for k in keys},
           "time_s": result.stats["total_s"], "density_evals": result.stats["density_evals"],
           **error, "reference_bound": ref.bound, "reference_rung": ref.rung,
           "reference_tolerance": ref.tolerance, "reference_dtype": ref.dtype, **every}
    return row, result.image[0]


def summarise(rows: Sequence[dict], settings: Sequence[dict], keys: Sequence[str]) -> list[dict]:
    """A row per setting over its samples: mean and standard deviation (0 for one sample) of time
    and RMSE, the worst RMSE, the largest reference bound, the mean density evaluations."""
    out = []
    for values in settings:
        mine = [r for r in rows if all(_text(r[k]) == (_text(values[k]) if k in values else "") for k in keys)]
        times, errors = [r["time_s"] for r in mine], [r["rmse"] for r in mine]

        def spread(xs: list[float]) -> float:
            return statistics.stdev(xs) if len(xs) > 1 else 0.0

        out.append({**{k: _cell(values[k]) if k in values else "" for k in keys}, "samples": len(mine),
                    "time_s_mean": statistics.fmean(times), "time_s_std": spread(times),
                    "rmse_mean": statistics.fmean(errors), "rmse_std": spread(errors), "rmse_max": max(errors),
                    "rel_rmse_mean": statistics.fmean(r["rel_rmse"] for r in mine),
                    "reference_bound_max": max(r["reference_bound"] for r in mine),
                    "every_order_rel_rmse_mean": _mean_or_blank([r["every_order_rel_rmse"] for r in mine]),
                    "density_evals_mean": statistics.fmean(r["density_evals"] for r in mine)})
    return out


def _mean_or_blank(values: list) -> float | str:
    """The mean of the values measured (blank: none)."""
    measured = [v for v in values if v != ""]
    return statistics.fmean(measured) if measured else ""


def _write_csv(path: Path, rows: Sequence[dict]) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def verdict(summary: Sequence[dict], keys: Sequence[str], *, max_error: float) -> str:
    """One line: the cheapest setting of the swept approximations (mean time) whose worst RMSE, over
    every sample and every swept scene value, is within `max_error`."""
    approx = [k for k in keys if is_approximation(k)] or list(keys)
    choices: dict[tuple, list[dict]] = {}
    for s in summary:
        choices.setdefault(tuple(s[k] for k in approx), []).append(s)

    def name(choice: tuple) -> str:
        return ", ".join(f"{k}={v}" for k, v in zip(approx, choice) if v != "")

    def figures_of(entries: list[dict]) -> tuple[float, float, float]:
        n = sum(e["samples"] for e in entries)
        return (sum(e["time_s_mean"] * e["samples"] for e in entries) / n, max(e["rmse_max"] for e in entries),
                max(e["reference_bound_max"] for e in entries))

    measured = {c: figures_of(e) for c, e in choices.items()}
    samples = max(s["samples"] for s in summary)
    across = ([f"{samples} samples"] if samples > 1 else []) + [f"every {k}" for k in keys if k not in approx]
    over = f" (worst over {' and '.join(across)})" if across else ""
    within = {c: m for c, m in measured.items() if m[1] <= max_error}
    if not within:
        best = min(measured, key=lambda c: measured[c][1])
        time_s, worst, bound = measured[best]
        return (f"no setting is within RMSE {max_error:.2g}: the most accurate, {name(best)}, has RMSE "
                f"{worst:.2g}{over} (reference bound {bound:.1g}), {time_s:.3g} s per render")
    best = min(within, key=lambda c: within[c][0])
    time_s, worst, bound = within[best]
    return (f"cheapest within RMSE {max_error:.2g}{' (8-bit quantisation)' if max_error == QUANTISATION_RMSE else ''}: "
            f"{name(best)}, {time_s:.3g} s per render, RMSE {worst:.2g}{over} (reference bound {bound:.1g})")


def _figures(out: Path, settings: list[dict], keys: list[str], summary: list[dict], rows: list[dict],
             groups: dict[str, list[dict]], first: dict, seed: int, cache: Path, max_error: float) -> list[Path]:
    """The figures of sample 0 (`first`, rendered with seed `seed`: contact sheet, difference) and
    of the summary (Pareto, per key)."""
    images = {n: torch.from_numpy(np.load(out / "images" / f"{n:03d}.npy")) for n in range(len(settings))
              if (out / "images" / f"{n:03d}.npy").is_file()}
    first_rows = {settings.index(v): r for v, r in zip(settings, rows)}  # rows of sample 0 come first
    references = []
    for group in groups.values():
        scene_values = {k: v for k, v in group[0].items() if not is_approximation(k)}
        spp = max(at_level(load_scene(setting_data(first, v))).image.spp for v in group)
        ladder = Ladder(setting_data(first, scene_values), seed=seed, spp=spp, cache=cache)
        ladder.k = max(first_rows[settings.index(v)]["reference_rung"] for v in group)
        references.append((scene_values, group, ladder.reference()))
    written = []
    tiles = [([f"{k}={_text(v)}" for k, v in values.items()]
              + [f"{first_rows[n]['time_s']:.3g} s, RMSE {first_rows[n]['rmse']:.2g} ± {first_rows[n]['reference_bound']:.1g}"],
              images[n]) for n, values in enumerate(settings) if n in images]
    tiles += [(["reference"] + [f"{k}={_text(v)}" for k, v in sv.items()] + [f"rung {ref.rung}, bound {ref.bound:.1g}"],
               ref.image[0]) for sv, _, ref in references]
    if tiles:
        figures.contact_sheet(tiles, out / "contact_sheet.png")
        written.append(out / "contact_sheet.png")
    worst = max((n for n in images), key=lambda n: first_rows[n]["rmse"], default=None)
    if worst is not None:
        ref = next(r for _, group, r in references if settings[worst] in group)
        figures.difference(images[worst], ref.image[0], out / "difference.png",
                           title=f"{label(settings[worst])}: RMSE {first_rows[worst]['rmse']:.2g} "
                                 f"(reference bound {ref.bound:.1g})")
        written.append(out / "difference.png")
    figures.pareto(summary, keys, out / "pareto.png", scene_keys=[k for k in keys if not is_approximation(k)], max_error=max_error)
    written.append(out / "pareto.png")
    written += figures.key_plots(summary, keys, out)
    return written
