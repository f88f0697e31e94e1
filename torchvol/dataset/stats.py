"""`torchvol stats DIR`: quality checks of a generated dataset (folder or webdataset layout).

Reads meta.json, manifest.jsonl and every sample's image, alpha and depth; writes DIR/stats.png
(distributions of the drawn parameters and of image statistics), DIR/stats.json and DIR/stats.md,
and flags a degenerate recipe: more than `max_share` of its images empty or saturated.

Statistics are per *image*: a sample holding several images (leading view or frame axes, e.g.
image (V, 3, H, W)) counts each of them. With the stored 8-bit image x in [0, 1] (H·W pixels, 3
channels), alpha a and depth d of one image:

- mean radiance: mean of x over pixels and channels (display-referred, after tone mapping);
- alpha coverage: mean of a over pixels;
- hit share: share of pixels with a valid depth (finite and > 0; 0 marks "nothing hit");
- clipped share: share of pixels with any channel at 1.0 (8-bit 255);
- empty: (alpha coverage < `empty_alpha` and hit share < `empty_alpha`: nothing but the sky) or
  the image is nearly constant (every channel's standard deviation over pixels < 1/255);
- saturated: clipped share > `saturated_pixels`.

The depth quantiles and histogram pool the valid depths of every sample (evenly strided down to
`DEPTHS_PER_SAMPLE` a sample, so that memory stays bounded for large datasets).
"""

from __future__ import annotations

import json
import tarfile
from collections import Counter
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from ..schema.validate import fail
from .codec import decode_file

EMPTY_ALPHA = 0.01  # alpha coverage and hit share under which an image shows nothing but the sky
CONSTANT_STD = 1.0 / 255.0  # a channel whose pixels vary less than one 8-bit step is constant
SATURATED_PIXELS = 0.10  # clipped share over which an image is saturated
MAX_SHARE = 0.10  # share of empty (or of saturated) images over which a recipe is degenerate
DEPTHS_PER_SAMPLE = 4096  # valid depths kept (evenly strided) per sample for the depth quantiles and histogram


def _records(root: Path) -> tuple[dict, list[dict]]:
    manifest = root / "manifest.jsonl"
    if not manifest.is_file():
        fail("DIR", str(root), "not a generated dataset (no manifest.jsonl; an unfinished `torchvol generate` "
             "is finished by running it again)")
    meta = json.loads((root / "meta.json").read_text()) if (root / "meta.json").is_file() else {}
    return meta, [json.loads(line) for line in manifest.read_text().splitlines() if line.strip()]


def _readers(root: Path, meta: dict, records: list[dict]) -> Iterator[tuple[dict, Callable[[str], bytes]]]:
    """(record, read(relative name) -> bytes) per sample: a folder's files or its shard's members."""
    if meta.get("layout", "folder") != "webdataset":
        for rec in records:
            yield rec, lambda rel: (root / rel).read_bytes()
        return
    by_shard: dict[str, list[dict]] = {}
    for rec in records:
        by_shard.setdefault(rec["shard"], []).append(rec)
    for shard, recs in sorted(by_shard.items()):
        with tarfile.open(root / "shards" / shard) as tar:
            members = {m.name: tar.extractfile(m).read() for m in tar.getmembers() if m.isfile()}
        for rec in recs:
            yield rec, members.__getitem__


def _label(read: Callable[[str], bytes], where: Any) -> np.ndarray:
    """A stored label as float32: one file, or a list of files (one per view or frame) stacked."""
    if isinstance(where, str):
        return decode_file(Path(where).name.split(".", 1)[1], read(where)).numpy()
    return np.stack([_label(read, w) for w in where])


def image_stats(image: np.ndarray, alpha: np.ndarray, depth: np.ndarray, *, empty_alpha: float = EMPTY_ALPHA,
                saturated_pixels: float = SATURATED_PIXELS) -> list[dict]:
    """Per-image statistics (module docstring). image (..., 3, H, W), alpha and depth (..., H, W) or
    (..., 1, H, W) with the same number of images; a sample whose labels disagree on it is one image."""
    h, w = image.shape[-2:]
    x, a, d = image.reshape(-1, 3, h * w), alpha.reshape(-1, h * w), depth.reshape(-1, h * w)
    if not len(x) == len(a) == len(d):
        x, a, d = x.transpose(1, 0, 2).reshape(1, 3, -1), a.reshape(1, -1), d.reshape(1, -1)
    out = []
    for xi, ai, di in zip(x, a, d):
        coverage, hit = float(ai.mean()), float((np.isfinite(di) & (di > 0)).mean())
        clipped = float((xi >= 1.0).any(axis=0).mean())
        constant = bool((xi.std(axis=1) < CONSTANT_STD).all())
        out.append({"mean_radiance": float(xi.mean()), "alpha_coverage": coverage, "hit_share": hit,
                    "clipped_share": clipped, "constant": constant,
                    "empty": constant or (coverage < empty_alpha and hit < empty_alpha),
                    "saturated": clipped > saturated_pixels})
    return out


def _param_values(value: Any) -> dict[str, Any] | None:
    """A drawn value as numeric components {suffix: [numbers]}: a number, or a vector (its last axis's
    components pooled over any leading axes, e.g. one eye per view); None if not numeric."""
    if isinstance(value, bool) or value is None:
        return None
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    if array.ndim == 0:
        return {"": [float(array)]}
    if array.size == 0:
        return None
    if array.shape[-1] > 4:
        return {"": array.ravel().tolist()}
    array = array.reshape(-1, array.shape[-1])
    return {f"[{c}]": array[:, c].tolist() for c in range(array.shape[1])}


def param_distributions(records: list[dict]) -> dict[str, dict]:
    """Per drawn key: {"kind": "numeric", "components": {suffix: [values]}} when every sample drew a
    number or vector, else {"kind": "choice", "counts": {label: n}} (strings, tables, mixed)."""
    keys: dict[str, list] = {}
    for rec in records:
        for key, value in (rec.get("params") or {}).items():
            keys.setdefault(key, []).append(value)
    out = {}
    for key, values in keys.items():
        numeric = [_param_values(v) for v in values]
        if all(n is not None and n.keys() == numeric[0].keys() for n in numeric):
            comps = {s: [x for n in numeric for x in n[s]] for s in numeric[0]}
            out[key] = {"kind": "numeric", "components": comps}
        else:
            labels = [v if isinstance(v, str) else json.dumps(v, sort_keys=True) for v in values]
            out[key] = {"kind": "choice", "counts": dict(Counter(labels))}
    return out


def dataset_stats(root: str | Path, *, empty_alpha: float = EMPTY_ALPHA, saturated_pixels: float = SATURATED_PIXELS,
                  max_share: float = MAX_SHARE) -> dict:
    """The statistics of the dataset in `root` (no files written): summary, per-image rows,
    parameter distributions, depth values and the warnings of a degenerate recipe."""
    for name, value in (("empty_alpha", empty_alpha), ("saturated_pixels", saturated_pixels), ("max_share", max_share)):
        if not 0.0 <= value <= 1.0:
            fail(name, value, "expected a share in [0, 1]")
    root = Path(root)
    meta, records = _records(root)
    if not records:
        fail("DIR", str(root), "holds no samples")
    rows, depths = [], []
    for rec, read in _readers(root, meta, records):
        files = rec["files"]
        image, alpha, depth = (_label(read, files[k]) for k in ("image", "alpha", "depth"))
        for view, row in enumerate(image_stats(image, alpha, depth, empty_alpha=empty_alpha,
                                               saturated_pixels=saturated_pixels)):
            rows.append({"index": rec["index"], "image": view, **row})
        valid = depth[np.isfinite(depth) & (depth > 0)].ravel()
        depths.append(valid[::-(-valid.size // DEPTHS_PER_SAMPLE) or 1])
    depth = np.concatenate(depths)
    n = len(rows)
    empty, saturated = sum(r["empty"] for r in rows), sum(r["saturated"] for r in rows)
    summary = {
        "samples": len(records), "images": n,
        "empty_share": empty / n, "saturated_share": saturated / n,
        "mean_radiance": float(np.mean([r["mean_radiance"] for r in rows])),
        "alpha_coverage": float(np.mean([r["alpha_coverage"] for r in rows])),
        "hit_share": float(np.mean([r["hit_share"] for r in rows])),
        "depth": ({q: float(v) for q, v in zip(("min", "p05", "median", "p95", "max"),
                                               np.quantile(depth, [0, 0.05, 0.5, 0.95, 1]))} if depth.size else None),
    }
    warnings = [f"{what}: {share:.0%} of the {n} images are {what} (more than {max_share:.0%})"
                for what, share in (("empty", summary["empty_share"]), ("saturated", summary["saturated_share"]))
                if share > max_share]
    return {
        "dataset": str(root), "recipe": root.name,
        "thresholds": {"empty_alpha": empty_alpha, "constant_std": CONSTANT_STD, "saturated_pixels": saturated_pixels,
                       "max_share": max_share},
        "summary": summary, "flagged": bool(warnings), "warnings": warnings, "images": rows,
        "params": param_distributions(records), "_depths": depth,
    }


def markdown(stats: dict) -> str:
    """One Markdown table row per dataset, with its header (`table_header()`)."""
    return table_header() + "\n" + table_row(stats) + "\n"


def table_header() -> str:
    """The header of `table`'s Markdown table (two lines)."""
    return ("| recipe | images | empty % | saturated % | mean radiance | alpha coverage | hit share | flagged |\n"
            "| --- | ---: | ---: | ---: | ---: | ---: | ---: | --- |")


def table_row(stats: dict) -> str:
    """One dataset's row of `table`, from its `stats` (`dataset_stats`'s summary and warnings)."""
    s = stats["summary"]
    return (f"| {stats['recipe']} | {s['images']} | {100 * s['empty_share']:.1f} | {100 * s['saturated_share']:.1f} | "
            f"{s['mean_radiance']:.3f} | {s['alpha_coverage']:.3f} | {s['hit_share']:.3f} | "
            f"{'**yes**: ' + '; '.join(stats['warnings']) if stats['flagged'] else 'no'} |")


def plot(stats: dict, path: str | Path) -> None:
    """stats.png: image statistics (mean radiance, alpha coverage, clipped share, depth), then one
    panel per drawn key (numbers as histograms, one colour per vector component; choices as bars)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = stats["images"]
    panels: list[tuple[str, Callable]] = []

    def hist(values, **kw):
        return lambda ax: ax.hist(values, bins=20, **kw)

    for key, label in (("mean_radiance", "mean radiance (display [0, 1])"), ("alpha_coverage", "alpha coverage"),
                       ("clipped_share", "clipped share (pixels at 1.0)")):
        panels.append((label, hist([r[key] for r in rows], range=(0.0, 1.0), color="tab:blue")))
    depth = stats["_depths"]
    panels.append(("depth (valid: finite, > 0)", hist(depth, color="tab:gray") if depth.size else
                   (lambda ax: ax.text(0.5, 0.5, "no valid depth", ha="center", transform=ax.transAxes))))
    for key, dist in stats["params"].items():
        if dist["kind"] == "numeric":
            def draw(ax, comps=dist["components"]):
                for suffix, values in comps.items():
                    ax.hist(values, bins=20, histtype="step" if len(comps) > 1 else "bar", label=suffix or None)
                if len(comps) > 1:
                    ax.legend(fontsize=6)
        else:
            def draw(ax, counts=dist["counts"]):
                labels = list(counts)
                ax.bar(range(len(labels)), [counts[k] for k in labels], color="tab:orange")
                short = all(len(k) <= 18 for k in labels)  # tables are numbered: stats.json has them in full
                ax.set_xticks(range(len(labels)), labels if short else [f"#{k}" for k in range(len(labels))],
                              rotation=30 if short else 0, ha="right" if short else "center", fontsize=6)
        panels.append((key, draw))
    cols = 4
    nrows = -(-len(panels) // cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(3.2 * cols, 2.4 * nrows), squeeze=False)
    for ax, (title, draw) in zip(axes.ravel(), panels):
        draw(ax)
        ax.set_title(title if len(title) <= 40 else "…" + title[-39:], fontsize=8)
        ax.tick_params(labelsize=6)
    for ax in axes.ravel()[len(panels):]:
        ax.axis("off")
    s = stats["summary"]
    fig.suptitle(f"{stats['recipe']}: {s['images']} images, empty {s['empty_share']:.0%}, "
                 f"saturated {s['saturated_share']:.0%}" + ("  DEGENERATE" if stats["flagged"] else ""), fontsize=10)
    inch = 2.4 * nrows  # margins in inches: the title above, rotated labels below
    fig.subplots_adjust(left=0.05, right=0.98, bottom=0.55 / inch, top=1 - 0.7 / inch, hspace=0.75, wspace=0.3)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_stats(root: str | Path, *, out: str | Path | None = None, **thresholds: float) -> dict:
    """Compute the statistics and write `out` (default DIR/stats.png), DIR/stats.json and DIR/stats.md."""
    stats = dataset_stats(root, **thresholds)
    root = Path(root)
    png = root / "stats.png" if out is None else Path(out)
    png.parent.mkdir(parents=True, exist_ok=True)
    plot(stats, png)
    public = {k: v for k, v in stats.items() if not k.startswith("_")}
    public["params"] = {key: dist if dist["kind"] == "choice" else
                        {"kind": "numeric", **{name: {s: float(f(np.asarray(v))) for s, v in dist["components"].items()}
                                               for name, f in (("min", np.min), ("mean", np.mean), ("max", np.max))}}
                        for key, dist in stats["params"].items()}
    (root / "stats.json").write_text(json.dumps(public, indent=1) + "\n")
    (root / "stats.md").write_text(markdown(stats))
    return {**stats, "written": [str(png), str(root / "stats.json"), str(root / "stats.md")]}
