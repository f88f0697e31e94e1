"""`torchvol sweep`: render every combination of swept values; time, cost and error per combination.

Error is measured against a reference-quality render of the same scene (`march.quality =
"reference"`, the scene's own step, shadow-step and spp settings removed: `at_quality`). Swept
`march.*` keys only change the approximation, so the reference is rendered once per distinct
combination of the other keys. Writes DIR/results.csv, DIR/contact_sheet.png (each cell labelled
with its values) and one DIR/plot_<key>.png per swept key (time and error against that key).
"""

from __future__ import annotations

import copy
import csv
import itertools
import math
import re
from pathlib import Path
from typing import Any, Mapping, Sequence

import torch

from .quality import Quality
from .keypath import set_path
from .scene import Scene, load_scene, read_source
from .validate import fail

# march keys that only set the approximation: the reference replaces them with its own
APPROXIMATION_KEYS = ("quality", "placement", "steps", "step_size", "step_growth", "dither", "dither_scale",
                      "min_transmittance", "density_threshold", "lod")


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


def reference_overrides(base: Mapping, quality: Quality = "reference") -> dict:
    """The march table at `quality`: approximation keys removed (the alpha integrator is kept: it
    is the shader look, not an approximation)."""
    march = {k: v for k, v in dict(base.get("march") or {}).items() if k not in APPROXIMATION_KEYS}
    if march.get("integrator") != "alpha":
        march.pop("integrator", None)
    march["quality"] = quality
    return march


def at_quality(data: Mapping, quality: Quality) -> dict:
    """A scene dict at level `quality` with every key the level decides removed, so the level sets
    it: the march's approximation keys, `image.spp`, lights' and voxels' `shadow.steps`,
    `voxels.max_steps`, `voxels.fog.shadow_steps`, `sky.atmosphere.steps` and `.light_steps`."""
    data = copy.deepcopy(dict(data))
    data["march"] = reference_overrides(data, quality)
    (data.get("image") or {}).pop("spp", None)
    voxels = data.get("voxels") or {}
    for shadow in [light.get("shadow") for light in data.get("lights") or []] + [voxels.get("shadow")]:
        if shadow:
            shadow.pop("steps", None)
    voxels.pop("max_steps", None)
    (voxels.get("fog") or {}).pop("shadow_steps", None)
    atmosphere = (data.get("sky") or {}).get("atmosphere") or {}
    for key in ("steps", "light_steps"):
        atmosphere.pop(key, None)
    return data


def image_error(image: torch.Tensor, reference: torch.Tensor) -> dict[str, float]:
    """RMSE, RMSE relative to the reference's RMS, and PSNR (kornia, peak 1) of `image` against
    `reference`, both (B, 3, H, W) in [0, 1]."""
    from kornia.metrics import psnr

    image, reference = image.float(), reference.float()
    mse = torch.mean((image - reference) ** 2).item()
    rms = math.sqrt(torch.mean(reference**2).item())
    return {"rmse": math.sqrt(mse), "rel_rmse": math.sqrt(mse) / rms if rms > 0 else math.inf,
            "psnr": float(psnr(image, reference, 1.0)) if mse > 0 else math.inf}


def sweep(scene: str | Path | Mapping | Scene, params: Mapping[str, Sequence[Any]], *, out: str | Path,
          seed: int = 0, overrides: Mapping[str, Any] | None = None) -> list[dict]:
    """Render every combination of `params` ({key path: [values]}) over `scene` (+ `overrides`);
    write results, contact sheet and plots to `out`. Returns the result rows."""
    from .render import render

    if not params:
        fail("--param", params, "give at least one KEY=V1,V2,... to sweep")
    for key, values in params.items():
        if not isinstance(values, (list, tuple)) or not values:
            fail(f"--param {key}", values, "expected a non-empty list of values")
    base = read_source(scene)
    for key, value in (overrides or {}).items():
        set_path(base, key, value)
    load_scene(base)  # validated once, with key paths, before any rendering
    keys = list(params)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    references: dict[tuple, torch.Tensor] = {}
    rows, images = [], []
    for combo in itertools.product(*(params[k] for k in keys)):
        values = dict(zip(keys, combo))
        s = load_scene(base, values)
        result = render(s, seed=seed)
        other = tuple((k, repr(v)) for k, v in values.items() if not k.startswith("march."))
        if other not in references:
            ref_data = copy.deepcopy(base)
            for k, v in values.items():
                if not k.startswith("march."):
                    set_path(ref_data, k, v)
            references[other] = render(load_scene(at_quality(ref_data, "reference")), seed=seed).image
        error = image_error(result.image, references[other])
        rows.append({
            **{k: _cell(v) for k, v in values.items()},
            "time_s": result.stats["total_s"],
            "density_evals": result.stats["density_evals"],
            "rmse": error["rmse"],
            "psnr": error["psnr"],
        })
        images.append((values, result.image[0]))
    with open(out / "results.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    contact_sheet(images, out / "contact_sheet.png")
    plot(rows, keys, out)
    return rows


def _cell(value: Any) -> Any:
    return value if isinstance(value, (int, float, str)) else repr(value)


def contact_sheet(images: Sequence[tuple[dict, torch.Tensor]], path: Path, *, columns: int | None = None) -> None:
    """A grid of the renders, each upscaled to at least 160 px wide and labelled with its values."""
    from PIL import Image, ImageDraw

    from .data import to_uint8

    h, w = images[0][1].shape[1:]
    scale = max(1, math.ceil(160 / w))
    lines = max(len(v) for v, _ in images)
    label_h = 12 * lines + 4
    cw, ch = w * scale, h * scale + label_h
    columns = columns or math.ceil(math.sqrt(len(images)))
    rows = math.ceil(len(images) / columns)
    sheet = Image.new("RGB", (columns * cw, rows * ch), "white")
    draw = ImageDraw.Draw(sheet)
    for n, (values, image) in enumerate(images):
        x, y = (n % columns) * cw, (n // columns) * ch
        tile = Image.fromarray(to_uint8(image.permute(1, 2, 0))).resize((cw, h * scale), Image.NEAREST)
        sheet.paste(tile, (x, y))
        for k, (key, value) in enumerate(values.items()):
            draw.text((x + 2, y + h * scale + 2 + 12 * k), f"{key}={value}", fill="black")
    sheet.save(path)


def plot(rows: Sequence[dict], keys: Sequence[str], out: Path) -> None:
    """One figure per swept key: time and RMSE against its values (one point per combination)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for key in keys:
        values = [r[key] for r in rows]
        numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
        labels = list(dict.fromkeys(values))
        xs = values if numeric else [labels.index(v) for v in values]
        fig, axes = plt.subplots(1, 2, figsize=(8, 3.2))
        for ax, metric, name in ((axes[0], "time_s", "time (s)"), (axes[1], "rmse", "RMSE vs reference")):
            ax.plot(xs, [r[metric] for r in rows], "o")
            ax.set_xlabel(key)
            ax.set_ylabel(name)
            if not numeric:
                ax.set_xticks(range(len(labels)), [str(v) for v in labels])
        fig.tight_layout()
        fig.savefig(out / f"plot_{re.sub(r'[^A-Za-z0-9_.-]+', '_', key).strip('_')}.png", dpi=80)
        plt.close(fig)
