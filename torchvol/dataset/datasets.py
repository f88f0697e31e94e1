"""Datasets: SceneDataset renders recipe samples on the fly; FolderDataset reads a generated folder.

One sample is a dict: image (3,H,W) float32 in [0,1], depth (1,H,W) float32 (planar z, 0 = no hit),
alpha (1,H,W), K (3,3), world_to_camera (4,4), index, seed, params (the drawn values by key path)
and the recipe's AOVs (C,H,W). With `[dataset] views = V` > 1 the image, depth, alpha, camera and
AOV tensors gain a leading V axis (`views.py`); with `volume_label` the sample adds
`extinction` (N,N,N) and `extinction_box` (2,3) (`volume_label.py`). `codec.py` turns one into
named files and back. A sequence recipe's samples (`[dataset] frames`) gain a leading frame axis
and `flow` (`sequence.py`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping, Sequence

import torch
from torch.utils.data import Dataset

from ..renderer.prepare import group
from ..runtime.compilation import CompileMode, compile_mode
from ..runtime.process import tune_process
from ..schema.validate import fail, integer, is_integer
from .codec import decode_file
from .distributions import mix_seed
from .recipe import Recipe, render_seed
from .views import sample_params, stack_views, view_params
from .volume_label import check_scene, extinction_of


def epoch_seed(seed: int, epoch: int | None) -> int:
    """The seed a dataset draws from: `seed` itself, or mixed with `epoch` for fresh samples."""
    return seed if epoch is None else mix_seed("torchvol.epoch", int(seed), int(epoch)) % 2**31


def render_samples(recipe: Recipe, indices: Sequence[int], *, seed: int = 0, aovs: Sequence[str] | None = None,
                   chunk_rays: int | None = None, compile: CompileMode | bool | None = "kernels") -> list[dict]:
    """Samples `indices` of `recipe`, rendered as few batches as possible (one per scene structure,
    e.g. one per phase kind a `choice` can give). A sample's values do not depend on its batch.
    `compile` (`torchvol.runtime.compilation`): "kernels" (True) or "off" (False, None: eager)."""
    from ..renderer.executor import DEFAULT_CHUNK_RAYS, render
    from .sequence import (  # its flow loads kornia: only when a recipe has frames
        add_flow,
        sequence_scenes,
    )

    aovs = recipe.aovs if aovs is None else tuple(aovs)
    compile = compile_mode(compile)
    if recipe.sequence is not None:  # frames > 1: a sample's frames are rendered like views, then its flow
        scenes, params = sequence_scenes(recipe, indices, seed=seed)
    elif recipe.views > 1:  # each sample's views
        drawn = [view_params(recipe, int(i), seed) for i in indices]
        scenes = [[recipe._scene(p) for p in views] for views in drawn]
        params = [sample_params(recipe, views) for views in drawn]
    else:  # (a mixed recipe's samples come from their family's recipe)
        drawn = [recipe.sample_with_params(int(i), seed) for i in indices]
        scenes, params = [[scene] for scene, _ in drawn], [p for _, p in drawn]
    if recipe.volume_label is not None:  # refused before anything renders
        for views in scenes:
            check_scene(views[0], recipe.volume_label)
    # every view or frame of every sample of one structure goes in one batch, levelled and keyed once
    flat = [(k, v) for k, views in enumerate(scenes) for v in range(len(views))]
    rendered: list[list[dict | None]] = [[None] * len(views) for views in scenes]
    labels: list[tuple | None] = [None] * len(scenes)
    for positions, batch in group([scenes[k][v] for k, v in flat]):
        members = [flat[i] for i in positions]
        out = render(batch, seed=[render_seed(int(indices[k]), seed) for k, _ in members],
                     chunk_rays=chunk_rays or DEFAULT_CHUNK_RAYS, aovs=aovs, compile=compile,
                     keep_context=recipe.volume_label is not None)
        missing = [a for a in aovs if a != "radiance" and a not in out.aovs]
        if missing:
            fail("dataset.aovs", missing, f"this scene does not compute them; it gives: {sorted(out.aovs) + ['radiance']}")
        for b, (k, v) in enumerate(members):
            rendered[k][v] = sample_tensors(out, b, aovs)
            if v == 0 and recipe.volume_label is not None:  # from the render's own fields
                labels[k] = extinction_of(out.context, b, recipe.volume_label)
    items = []
    for k, views in enumerate(rendered):
        tensors = stack_views(views)
        item = {key: tensors.pop(key) for key in ("image", "depth", "alpha", "K", "world_to_camera")}
        item.update(index=int(indices[k]), seed=int(seed), params=params[k], **tensors)
        if recipe.sequence is not None:
            add_flow(item)
        if labels[k] is not None:
            item["extinction"], item["extinction_box"] = labels[k]
        items.append(item)
    return items


def sample_tensors(out, b: int, aovs: Sequence[str]) -> dict[str, torch.Tensor]:
    """Scene `b` of a render's output `out` as a sample's tensors: image (3, H, W), depth and alpha
    (1, H, W), K (3, 3), world_to_camera (4, 4) and the AOVs `aovs` (C, H, W), float32, contiguous."""
    extra = {a: (out.radiance if a == "radiance" else out.aovs[a])[b].float().contiguous() for a in aovs}
    return {
        "image": out.image[b].float().contiguous(),
        "depth": out.depth[b].float().contiguous(),
        "alpha": out.alpha[b].float().contiguous(),
        "K": out.camera.K[b].float().contiguous(),
        "world_to_camera": out.camera.world_to_camera[b].float().contiguous(),
        **extra,
    }


class SceneDataset(Dataset):
    """Map-style dataset of `length` samples of `recipe` (a Recipe or anything Recipe.load takes).

    ds[i] depends only on (seed, epoch, i): the same in any process, DataLoader worker or order.
    `epoch` (optional) mixes into the seed so that each epoch draws fresh scenes. `compile`
    (`torchvol.runtime.compilation`): "kernels" (True, the default) runs Dr.Jit's kernels wherever
    they render a technique, the same bytes as `torchvol generate`; "off" (False, None) renders the
    eager reference, as `torchvol generate --eager` does. A DataLoader's workers:
    `worker_init_fn=SceneDataset.worker_init_fn` tunes each (`tune_process`)."""

    def __init__(self, recipe: Recipe | str | Path | Mapping, length: int, seed: int = 0, epoch: int | None = None, *,
                 aovs: Sequence[str] | None = None, overrides: Mapping[str, Any] | None = None,
                 compile: CompileMode | bool | None = "kernels"):
        integer("length", length, low=0)
        integer("seed", seed)
        if epoch is not None and not is_integer(epoch):
            fail("epoch", epoch, "expected an integer or None")
        self.recipe = Recipe.load(recipe, overrides)
        self.length, self.base_seed, self.epoch = length, seed, epoch
        self.seed = epoch_seed(seed, epoch)
        self.aovs = self.recipe.aovs if aovs is None else tuple(aovs)
        self.compile = compile_mode(compile)

    def __len__(self) -> int:
        return self.length

    def _check(self, index: int) -> int:
        if not is_integer(index) or not -self.length <= index < self.length:
            raise IndexError(f"index {index!r} out of range for a dataset of {self.length}")
        return int(index) % self.length if self.length else int(index)

    def __getitem__(self, index: int) -> dict:
        return self.batch([index])[0]

    def batch(self, indices: Sequence[int]) -> list[dict]:
        """Several samples rendered as one batch (the generator's path); same values as ds[i]."""
        return render_samples(self.recipe, [self._check(i) for i in indices], seed=self.seed, aovs=self.aovs,
                              compile=self.compile)

    @staticmethod
    def worker_init_fn(worker_id: int) -> None:
        """A DataLoader `worker_init_fn`: `tv.tune_process()` in each worker (its heap: spawned
        workers do not inherit it; OpenMP's wait policy is the parent's, set before torch loads)."""
        tune_process()


def collate(items: Sequence[dict]) -> dict:
    """DataLoader collate: tensors stacked, index/seed as tensors, params kept as a list of dicts
    (drawn values may be vectors, strings or tables, which the default collate cannot stack)."""
    out: dict[str, Any] = {}
    for key in items[0]:
        values = [item[key] for item in items]
        if key == "params":
            out[key] = values
        elif isinstance(values[0], torch.Tensor):
            out[key] = torch.stack(values)
        else:
            out[key] = torch.tensor(values)
    return out


class FolderDataset(Dataset):
    """A folder written by `torchvol generate --format folder`, read back with SceneDataset's keys
    and dtypes (float32). image and alpha are 8-bit (quantised); depth and AOVs are exact, but uv
    (float16: within 2.4e-4)."""

    def __init__(self, path: str | Path):
        self.root = Path(path)
        manifest = self.root / "manifest.jsonl"
        if not manifest.is_file():
            fail("path", str(path), "not a generated dataset folder (no manifest.jsonl)")
        self.meta = json.loads((self.root / "meta.json").read_text()) if (self.root / "meta.json").is_file() else {}
        if self.meta.get("layout", "folder") != "folder":
            fail("path", str(path), f"holds a {self.meta.get('layout')!r} dataset; FolderDataset reads the folder layout")
        self.records = [json.loads(line) for line in manifest.read_text().splitlines() if line.strip()]

    def __len__(self) -> int:
        return len(self.records)

    def __getitem__(self, index: int) -> dict:
        rec = self.records[index]
        item: dict[str, Any] = {}
        for key, rel in rec["files"].items():
            if isinstance(rel, list):  # one file per view
                item[key] = torch.stack([self._read(r) for r in rel])
            else:
                item[key] = self._read(rel)
        item["K"] = torch.tensor(rec["K"], dtype=torch.float32)
        item["world_to_camera"] = torch.tensor(rec["world_to_camera"], dtype=torch.float32)
        item["index"], item["seed"], item["params"] = rec["index"], rec["seed"], rec["params"]
        return item

    def _read(self, rel: str) -> torch.Tensor:
        return decode_file(Path(rel).name.split(".", 1)[1], (self.root / rel).read_bytes())
