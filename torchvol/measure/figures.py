"""The sweep's figures: a Pareto plot of error against time, a labelled contact sheet, a difference
image against the reference, and time and error against each swept key (matplotlib, PIL, kornia)."""

from __future__ import annotations

import itertools
import math
import re
from pathlib import Path
from typing import Sequence

import numpy as np
from torch import Tensor

TILE_WIDTH = (192, 320)  # contact-sheet tiles are resampled into this range of widths
COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#7f7f7f", "#bcbd22")
MARKERS = ("o", "s", "^", "D", "v", "P", "X", "h", "<", ">")
LEVEL = "march.quality"


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def resample(image: Tensor, width: int) -> Tensor:
    """(3, h, w) in [0, 1] -> (3, h', width), bicubic with antialiasing (kornia), aspect kept."""
    from kornia.geometry.transform import resize

    h, w = image.shape[1:]
    if w == width:
        return image
    out = resize(image[None].float(), (max(1, round(h * width / w)), width), interpolation="bicubic", antialias=True)
    return out[0].clamp(0.0, 1.0)


def contact_sheet(tiles: Sequence[tuple[Sequence[str], Tensor]], path: Path, *, columns: int | None = None) -> None:
    """A grid of images (3, h, w) in [0, 1], each resampled smoothly to a width in TILE_WIDTH and
    labelled underneath with its lines of text (cells widen to the longest line)."""
    from PIL import Image, ImageDraw, ImageFont

    font = ImageFont.load_default(size=13)
    w = tiles[0][1].shape[2]
    width = min(max(w, TILE_WIDTH[0]), TILE_WIDTH[1])
    cell = max(width, max(math.ceil(font.getlength(line)) + 4 for lines, _ in tiles for line in lines))
    pictures = [resample(image, width) for _, image in tiles]
    height = max(p.shape[1] for p in pictures)
    line_h = 16
    label_h = line_h * max(len(lines) for lines, _ in tiles) + 6
    columns = columns or math.ceil(math.sqrt(len(tiles)))
    rows = math.ceil(len(tiles) / columns)
    pad = 4
    sheet = Image.new("RGB", (columns * (cell + pad) + pad, rows * (height + label_h + pad) + pad), "white")
    draw = ImageDraw.Draw(sheet)
    for n, ((lines, _), picture) in enumerate(zip(tiles, pictures)):
        x, y = pad + (n % columns) * (cell + pad), pad + (n // columns) * (height + label_h + pad)
        array = (picture.permute(1, 2, 0).numpy() * 255.0 + 0.5).astype(np.uint8)
        sheet.paste(Image.fromarray(array), (x, y))
        for k, line in enumerate(lines):
            draw.text((x + 2, y + picture.shape[1] + 3 + line_h * k), line, fill="black", font=font)
    sheet.save(path)


def difference(image: Tensor, reference: Tensor, path: Path, *, title: str) -> None:
    """The image, its reference (both (3, H, W)) and |image − reference| (largest over the
    channels, display-referred units) side by side, with a colour scale."""
    plt = _pyplot()
    diff = (image.float() - reference.float()).abs().amax(dim=0).numpy()
    h, w = diff.shape
    fig, axes = plt.subplots(1, 3, figsize=(3 * max(3.0, 3.0 * w / h) + 1.0, 3.6), constrained_layout=True)
    for ax, picture, name in ((axes[0], image, "setting"), (axes[1], reference, "reference")):
        ax.imshow(picture.permute(1, 2, 0).clamp(0, 1).numpy(), interpolation="bicubic")
        ax.set_title(name, fontsize=9)
    shown = axes[2].imshow(diff, cmap="magma", interpolation="nearest", vmin=0.0, vmax=max(float(diff.max()), 1e-12))
    axes[2].set_title("|setting − reference|", fontsize=9)
    fig.colorbar(shown, ax=axes[2], shrink=0.85)
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(title, fontsize=9)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _front(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The points no other point beats in both time and error, by time."""
    front, best = [], math.inf
    for t, e in sorted(points):
        if e < best:
            front.append((t, e))
            best = e
    return front


def pareto(summary: Sequence[dict], keys: Sequence[str], path: Path, *, scene_keys: Sequence[str], max_error: float) -> None:
    """Mean RMSE against mean time per render (log-log) for every setting of `summary`, with the
    spread over samples as error bars; colour, marker and size encode the first three swept keys
    (a legend each, further keys are written by the points), quality levels are black stars named
    by their level. A dashed line joins the Pareto front of each combination of `scene_keys` (the
    swept keys that change the scene, not its approximation); `max_error` is a dotted line."""
    plt = _pyplot()
    from matplotlib.lines import Line2D

    styled = [k for k in keys if k != LEVEL]
    values = {k: list(dict.fromkeys(s[k] for s in summary if s[k] != "")) for k in styled}
    scene = [k for k in styled if k in scene_keys]
    fig, ax = plt.subplots(figsize=(7.5, 4.6))
    floor = min((s["rmse_mean"] for s in summary if s["rmse_mean"] > 0), default=1e-6) / 2  # exact renders stay on log axes
    for s in summary:
        x, y = s["time_s_mean"], max(s["rmse_mean"], floor)
        level = s.get(LEVEL, "")
        if level != "":
            ax.errorbar(x, y, xerr=s["time_s_std"] or None, yerr=s["rmse_std"] or None, fmt="*", color="black", markersize=13)
            ax.annotate(f"{level}", (x, y), fontsize=8, xytext=(6, 4), textcoords="offset points")
            continue
        colour = COLOURS[values[styled[0]].index(s[styled[0]]) % len(COLOURS)] if styled else COLOURS[0]
        marker = MARKERS[values[styled[1]].index(s[styled[1]]) % len(MARKERS)] if len(styled) > 1 else "o"
        size = 6 + 3 * values[styled[2]].index(s[styled[2]]) if len(styled) > 2 else 7
        ax.errorbar(x, y, xerr=s["time_s_std"] or None, yerr=s["rmse_std"] or None, fmt=marker, color=colour,
                    markersize=size, markeredgecolor="black", markeredgewidth=0.5, ecolor=colour, elinewidth=0.8)
        if len(styled) > 3:
            ax.annotate(", ".join(f"{s[k]}" for k in styled[3:]), (x, y), fontsize=7, xytext=(5, -9), textcoords="offset points")
    for combo in itertools.product(*(values[k] for k in scene)):
        mine = [s for s in summary if all(s[k] == v for k, v in zip(scene, combo))]
        front = _front([(s["time_s_mean"], max(s["rmse_mean"], floor)) for s in mine])
        if len(front) > 1:
            ax.plot(*zip(*front), "--", color="0.6", linewidth=0.8, zorder=0)
    ax.axhline(max_error, color="0.3", linestyle=":", linewidth=1.0)
    ax.annotate(f"RMSE {max_error:.2g}", (0.01, max_error), xycoords=("axes fraction", "data"), fontsize=7,
                xytext=(0, 3), textcoords="offset points", color="0.3")
    ax.set(xscale="log", yscale="log", xlabel="time per render (s)", ylabel="RMSE against the reference")
    ratio = max((s["reference_bound_max"] / s["rmse_max"] for s in summary if s["rmse_max"] > 0), default=0.0)
    share = "under 1%" if ratio < 0.01 else f"at most {ratio:.0%}"
    ax.set_title(f"error against time; each reference's bound is {share} of the error it measures"
                 + ("; bars: spread over samples" if any(s["samples"] > 1 for s in summary) else ""), fontsize=9)
    handles = []  # one legend: a heading per swept key, then its values in the key's encoding
    for n, k in enumerate(styled[:3]):
        handles.append(Line2D([], [], linestyle="", label=k))
        for i, v in enumerate(values[k]):
            style = [dict(marker="o", color=COLOURS[i % len(COLOURS)], markeredgecolor="black", markeredgewidth=0.5),
                     dict(marker=MARKERS[i % len(MARKERS)], color="0.5"), dict(marker="o", color="0.5", markersize=6 + 3 * i)][n]
            handles.append(Line2D([], [], linestyle="", label=f"  {v}", **style))
    if any(s.get(LEVEL, "") != "" for s in summary):
        handles.append(Line2D([], [], linestyle="", marker="*", color="black", markersize=11, label="quality level"))
    if handles:
        ax.legend(handles=handles, fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    fig.savefig(path, dpi=100, bbox_inches="tight")  # "tight": the legends sit outside the axes
    plt.close(fig)


def key_plots(summary: Sequence[dict], keys: Sequence[str], out: Path) -> list[Path]:
    """Per swept key, DIR/plot_<key>.png: mean time and RMSE against the key's values, a line (and
    a legend entry) per combination of the other swept keys."""
    plt = _pyplot()
    written = []
    for key in keys:
        mine = [s for s in summary if s[key] != ""]
        xs = list(dict.fromkeys(s[key] for s in mine))
        numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in xs)
        others = [k for k in keys if k != key]
        lines: dict[tuple, list[dict]] = {}
        for s in mine:
            lines.setdefault(tuple(s[k] for k in others), []).append(s)
        fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
        for n, (combo, points) in enumerate(lines.items()):
            name = ", ".join(f"{k}={v}" for k, v in zip(others, combo) if v != "") or "all"
            position = [s[key] if numeric else xs.index(s[key]) for s in points]
            for ax, metric in ((axes[0], "time_s_mean"), (axes[1], "rmse_mean")):
                ax.plot(position, [s[metric] for s in points], marker=MARKERS[n % len(MARKERS)],
                        color=COLOURS[n % len(COLOURS)], label=name)
        for ax, name in ((axes[0], "time per render (s)"), (axes[1], "RMSE against the reference")):
            ax.set_xlabel(key)
            ax.set_ylabel(name)
            ax.set_yscale("log")
            if numeric and min(xs) > 0 and max(xs) / min(xs) >= 8:
                ax.set_xscale("log", base=2)
            if not numeric:
                ax.set_xticks(range(len(xs)), [str(v) for v in xs])
        if len(lines) > 1:
            axes[1].legend(fontsize=7, loc="best")
        fig.tight_layout()
        path = out / f"plot_{re.sub(r'[^A-Za-z0-9_.-]+', '_', key).strip('_')}.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        written.append(path)
    return written
