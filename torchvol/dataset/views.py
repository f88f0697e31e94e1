"""Multi-view samples (`[dataset] views = V`): V cameras of one drawn scene, rendered as one batch.

Every value of a sample is drawn once, as for a single view, except the camera's: each key path
under `camera` that holds a distribution is drawn again for each view v >= 1 from a generator seeded
with (seed, index, key path, v). View 0 is the single-view draw itself, so view 0 of a multi-view
sample equals the sample of the same recipe with `views = 1`. A sample's tensors gain a leading V
axis when V > 1: image (V, 3, H, W), depth and alpha (V, 1, H, W), K (V, 3, 3), world_to_camera
(V, 4, 4), each AOV (V, C, H, W); with V = 1 they keep the single-view shapes.

Files: a view's files carry its index before the extension (`image.0.png`, `depth.0.npy`,
`alpha.0.png`, `<aov>.0.npz`, ...), so webdataset and Hugging Face `datasets` decode each by its
last extension; the manifest record lists the V paths of each key in view order.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping, Sequence

import torch

from ..schema.validate import fail, is_integer

# Views in one sample: each is a full render, so a typo (views = 4000) should not start one.
MAX_VIEWS = 256
MAX_RESOLUTION = 512
# Per-sample labels that have no view axis (the volume label, `torchvol.dataset.volume_label`).
VOLUME_KEYS = ("extinction", "extinction_box")


def camera_paths(dists: Mapping[str, Any]) -> list[str]:
    """The key paths of a recipe's distributions that belong to the camera (drawn per view)."""
    return [p for p in dists if p == "camera" or p.startswith(("camera.", "camera["))]


def parse_dataset(meta: Mapping[str, Any], dists: Mapping[str, Any]) -> tuple[int, int | None]:
    """(views, volume_label resolution or None) from a recipe's `[dataset]` table, validated."""
    views = meta.get("views", 1)
    if not is_integer(views) or not 1 <= views <= MAX_VIEWS:
        fail("dataset.views", views, f"expected an integer in [1, {MAX_VIEWS}] (cameras per sample)")
    if views > 1 and not camera_paths(dists):
        fail("dataset.views", views, "every view would be the same: give the camera a distribution "
             "(e.g. camera.eye = { orbit = { ... } }) so each view draws its own")
    label = meta.get("volume_label")
    if label is None:
        return int(views), None
    if not isinstance(label, Mapping) or set(label) != {"resolution"}:
        fail("dataset.volume_label", label, "expected a table { resolution = N }")
    n = label["resolution"]
    if not is_integer(n) or not 2 <= n <= MAX_RESOLUTION:
        fail("dataset.volume_label.resolution", n, f"expected an integer in [2, {MAX_RESOLUTION}] (cells per axis)")
    return int(views), int(n)


def view_params(recipe, index: int, seed: int) -> list[dict[str, Any]]:
    """The drawn values of each of the recipe's `views`: view 0's are `recipe.sample_params`; a later
    view redraws the camera's key paths with the view index in their generators' seeds."""
    first = recipe.sample_params(index, seed)
    out = [first]
    for v in range(1, recipe.views):
        redrawn = {p: recipe.dists[p].draw(seed, index, "view", v) for p in camera_paths(recipe.dists)}
        out.append({**first, **redrawn})
    return out


def sample_params(recipe, per_view: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """A sample's `params`: view 0's drawn values by key path; with several views, also `views`,
    the camera's drawn values of each view (a list of V {key path: value})."""
    if len(per_view) == 1:
        return dict(per_view[0])
    paths = camera_paths(recipe.dists)
    return {**per_view[0], "views": [{p: params[p] for p in paths} for params in per_view]}


def stack_views(views: Sequence[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """One sample's tensors from its V views' (each `image` (3, H, W), ...): the single view's as they
    are when V = 1, else stacked on a leading V axis."""
    if len(views) == 1:
        return dict(views[0])
    return {key: torch.stack([v[key] for v in views]) for key in views[0]}


def view_count(item: Mapping[str, Any]) -> int | None:
    """V for a multi-view sample (its image is (V, 3, H, W)), None for a single view."""
    return item["image"].shape[0] if item["image"].ndim == 4 else None


def encode_views(item: Mapping[str, Any], encode_one: Callable[[Mapping[str, Any]], dict[str, bytes]]) -> dict[str, bytes]:
    """A multi-view sample's files: each view's files from `encode_one` (image.png -> image.{v}.png)."""
    files: dict[str, bytes] = {}
    for v in range(view_count(item)):
        one = {k: x[v] for k, x in item.items() if isinstance(x, torch.Tensor) and k not in VOLUME_KEYS}
        for suffix, data in encode_one(one).items():
            key, ext = suffix.split(".", 1)
            files[f"{key}.{v}.{ext}"] = data
    return files


def file_table(suffixes: Sequence[str], prefix: str) -> dict[str, str | list[str]]:
    """The manifest's `files`: key -> `prefix + suffix`, or key -> [path of view 0, 1, ...] for
    per-view files (`image.0.png`, `image.1.png`, ...)."""
    table: dict[str, Any] = {}
    for suffix in suffixes:
        parts = suffix.split(".")
        if len(parts) == 3 and parts[1].isdigit():
            table.setdefault(parts[0], []).append((int(parts[1]), prefix + suffix))
        else:
            table[parts[0]] = prefix + suffix
    return {k: [p for _, p in sorted(v)] if isinstance(v, list) else v for k, v in table.items()}


def dataset_meta(recipe) -> dict[str, Any]:
    """meta.json's entries for the multi-view and volume-label settings (none at their defaults, so
    a dataset without them keeps its meta.json bytes)."""
    out: dict[str, Any] = {}
    if recipe.views > 1:
        out["views"] = recipe.views
    if recipe.volume_label is not None:
        out["volume_label"] = {
            "resolution": recipe.volume_label,
            "convention": "extinction.npy (N, N, N) float32: sigma_t * density summed over the volumes, per world "
                          "unit; [k, j, i] at the centre of cell (i, j, k) of extinction_box.npy (2, 3) float32 "
                          "(min, max corners; i along x, j along y, k along z), as grid media",
        }
    return out
