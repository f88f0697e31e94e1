"""`torchvol generate`: render N recipe samples into a folder or webdataset shards, resumably.

Layout (DIR):
  meta.json                 conventions, recipe, seed, count, layout (written first, atomically)
  manifest.jsonl            one record per sample, by index (written last, atomically)
  folder:      samples/{index:06d}.{image.png, depth.npy, alpha.png, <aov>.npz, json}
  webdataset:  shards/shard-{k:06d}.tar holding {index:06d}.{json, image.png, depth.npy, alpha.png, <aov>.npz}
  (`[dataset] views = V` > 1 or `frames = F` > 1: image.{v}.png, depth.{v}.npy, ... per view or frame,
  `torchvol.dataset.views`; sequences add flow.npz, flow_valid.npz, `torchvol.dataset.sequence`; `volume_label`:
  extinction.npy, extinction_box.npy, `torchvol.dataset.volume_label`)

Every file is written to a hidden temporary name and renamed into place, so a reader never sees a
partial file. A folder sample is finished when its .json record exists (written after its other
files); a shard when its .tar exists. A re-run of the same command skips finished work and gives a
result byte-identical to an uninterrupted run: a sample's bytes depend only on (recipe, seed, index),
never on its batch, worker or the run that rendered it.
"""

from __future__ import annotations

import io
import json
import os
import sys
import tarfile
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal, Mapping, Sequence

from ..runtime.compilation import CompileMode, compile_mode
from ..runtime.process import init_worker, tune_process
from ..runtime.progress import progress as bar
from ..runtime.threads import torch_threads
from ..schema.validate import fail, integer
from .codec import CONVENTIONS, sample_record
from .datasets import render_samples
from .recipe import Recipe
from .sequence import CONVENTIONS as SEQUENCE_CONVENTIONS
from .sequence import encode_item
from .views import dataset_meta, file_table

Layout = Literal["folder", "webdataset"]


def atomic_write(path: Path, data: bytes) -> None:
    """Write `data` to `path` through a hidden temporary file and os.replace (atomic on POSIX)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as f:
        f.write(data)
    os.replace(tmp, path)


def _json_bytes(obj: Any) -> bytes:
    return (json.dumps(obj, sort_keys=True, separators=(",", ":")) + "\n").encode()


def tar_bytes(members: Sequence[tuple[str, bytes]]) -> bytes:
    """A tar with fixed metadata (mtime 0, uid/gid 0, no user names, mode 0644), members in order,
    so the same members give the same bytes."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w", format=tarfile.USTAR_FORMAT) as tar:
        for name, data in members:
            info = tarfile.TarInfo(name)
            info.size, info.mtime, info.mode = len(data), 0, 0o644
            info.uid = info.gid = 0
            info.uname = info.gname = ""
            tar.addfile(info, io.BytesIO(data))
    return buf.getvalue()


@dataclass(frozen=True)
class Task:
    """One unit of work: indices rendered in batches of `batch`, written under `out`."""

    recipe: Recipe
    seed: int
    indices: tuple[int, ...]
    out: str
    layout: Layout
    batch: int
    shard: int
    compile: CompileMode = "kernels"  # Dr.Jit's kernels or the eager reference (torchvol.runtime.compilation)


def run_task(task: Task) -> list[int]:
    """Render and write one task; returns the indices it wrote (skipping finished ones)."""
    out = Path(task.out)
    aovs = task.recipe.aovs
    if task.layout == "folder":
        todo = [i for i in task.indices if not (out / "samples" / f"{i:06d}.json").is_file()]
        for first in range(0, len(todo), task.batch):
            part = todo[first:first + task.batch]
            for item in render_samples(task.recipe, part, seed=task.seed, compile=task.compile):
                stem = f"{item['index']:06d}"
                encoded = encode_item(item, aovs)
                for suffix, data in encoded.items():
                    atomic_write(out / "samples" / f"{stem}.{suffix}", data)
                files = file_table(list(encoded), f"samples/{stem}.")
                # the record last: its presence marks the sample finished
                atomic_write(out / "samples" / f"{stem}.json", _json_bytes(sample_record(item, files)))
        return todo
    path = out / "shards" / f"shard-{task.shard:06d}.tar"
    if path.is_file():
        return []
    members: list[tuple[str, bytes]] = []
    for first in range(0, len(task.indices), task.batch):
        for item in render_samples(task.recipe, task.indices[first:first + task.batch], seed=task.seed,
                                   compile=task.compile):
            stem = f"{item['index']:06d}"
            encoded = encode_item(item, aovs)
            files = file_table(list(encoded), f"{stem}.")
            record = {**sample_record(item, files), "shard": path.name}
            members.append((f"{stem}.json", _json_bytes(record)))
            members += [(f"{stem}.{suffix}", data) for suffix, data in encoded.items()]
    atomic_write(path, tar_bytes(members))
    return list(task.indices)


# rays one batch of samples renders when `generate` picks the batch, one render chunk: a batch's
# fixed costs (its plan, its scenes' tables and grids, each kernel's tracing in Python) are shared by
# its samples. CPU time a sample on one thread (`python tools/bench_batch.py`, docs/SPEED.md, "Batch
# size"): clouds (64²) 26.5 ms alone, 13.5 ms in batches of 4, 10.8 ms of 16; voxel-terrain (96×64)
# 47.0, 26.2 and 23.3 ms (of 8)
AUTO_BATCH_RAYS = 1 << 16


def auto_batch(recipe: Recipe, *, count: int, workers: int, seed: int) -> int:
    """The samples a batch renders by default: as many as fill `AUTO_BATCH_RAYS` rays (each
    sample's views and frames counted), in a number of batches that is a multiple of `workers`
    and at least two a worker, so that the workers finish together. A sample's bytes do not
    depend on it."""
    image = recipe.sample_with_params(0, seed)[0].image
    rays = image.width * image.height * recipe.views * (1 if recipe.sequence is None else recipe.sequence.frames)
    batches = max(2 * workers, -(-count // max(1, AUTO_BATCH_RAYS // rays)))
    return -(-count // (-(-batches // workers) * workers))


def plan_tasks(recipe: Recipe, *, count: int, seed: int, out: Path, layout: Layout, batch: int, shard_size: int) -> list[Task]:
    """The dataset's work as tasks in index order: a batch of `batch` samples each (folder), or a
    shard of `shard_size` samples each (webdataset)."""
    size = shard_size if layout == "webdataset" else batch
    return [Task(recipe, seed, tuple(range(s, min(count, s + size))), str(out), layout, batch, k)
            for k, s in enumerate(range(0, count, size))]


def _finished(task: Task) -> int:
    out = Path(task.out)
    if task.layout == "webdataset":
        return len(task.indices) if (out / "shards" / f"shard-{task.shard:06d}.tar").is_file() else 0
    return sum((out / "samples" / f"{i:06d}.json").is_file() for i in task.indices)


def _manifest(out: Path, layout: Layout, count: int) -> bytes:
    records: list[bytes] = []
    if layout == "folder":
        for i in range(count):
            records.append((out / "samples" / f"{i:06d}.json").read_bytes())
    else:
        for shard in sorted((out / "shards").glob("shard-*.tar")):
            with tarfile.open(shard) as tar:
                records += [tar.extractfile(m).read() for m in tar.getmembers() if m.name.endswith(".json")]
    return b"".join(records)


def generate(
    recipe: Recipe | str | Path | Mapping,
    *,
    count: int,
    out: str | Path,
    seed: int = 0,
    workers: int = 1,
    layout: Layout = "folder",
    overrides: Mapping[str, Any] | None = None,
    batch: int | None = None,
    shard_size: int = 64,
    threads: int | None = None,
    scheduler: str | None = None,
    progress: bool | None = None,
    stop_after: int | None = None,
    compile: CompileMode | bool | None = "kernels",
) -> dict:
    """Generate (or finish) the dataset in `out`. `workers` local processes (spawned, each with
    `threads` torch threads, tuned by `tune_process`; `workers=1` renders in this process and
    leaves it as it is), `batch` samples rendered together (None: `auto_batch`), or the Dask cluster at `scheduler` (its workers tuned too). `progress`: a bar of samples
    done on stderr (None: only when stderr is a terminal). `stop_after` (testing: simulates a kill)
    stops once that many samples were written, leaving the dataset unfinished. `compile`
    (`torchvol.runtime.compilation`): "kernels" (True, the default) runs Dr.Jit's kernels wherever
    they render a technique: the bytes are `SceneDataset`'s; "off" (False, None) renders the eager
    reference, recorded in meta.json (its bytes differ), so a resumed run renders as the first did.
    Returns {"written": samples rendered now, "count", "out"}."""
    for name, value in (("count", count), ("workers", workers), ("shard_size", shard_size)):
        integer(name, value, low=1)
    if batch is not None:
        integer("batch", batch, low=1)
    if threads is not None:
        integer("threads", threads, low=1)
    integer("seed", seed)
    if layout not in ("folder", "webdataset"):
        fail("layout", layout, "expected folder or webdataset")
    compile = compile_mode(compile)
    recipe = Recipe.load(recipe, overrides)
    batch = auto_batch(recipe, count=count, workers=workers, seed=seed) if batch is None else batch
    out = Path(out)
    open_dataset(out, dataset_meta_bytes(recipe, count=count, seed=seed, layout=layout, shard_size=shard_size,
                                         compile=compile), layout)
    tasks = [replace(t, compile=compile) for t in
             plan_tasks(recipe, count=count, seed=seed, out=out, layout=layout, batch=batch, shard_size=shard_size)]
    done = sum(_finished(t) for t in tasks)
    pending = [t for t in tasks if _finished(t) < len(t.indices)]
    written = 0
    with bar(count, initial=done, unit="sample", desc=f"generate {out.name}",
             enabled=sys.stderr.isatty() if progress is None else progress) as shown:
        for n in _execute(pending, workers=workers, threads=threads, scheduler=scheduler):
            written += n
            shown.update(n)
            if stop_after is not None and written >= stop_after:
                return {"written": written, "count": count, "out": str(out), "finished": False}
    atomic_write(out / "manifest.jsonl", _manifest(out, layout, count))
    return {"written": written, "count": count, "out": str(out), "finished": True}


def dataset_meta_bytes(recipe: Recipe, *, count: int, seed: int, layout: Layout, shard_size: int, compile: str) -> bytes:
    """meta.json's bytes for a dataset of `count` samples of `recipe`: what a resumed run must
    match exactly (recipe, seed, count, layout, shard size, conventions, compile where it changes bytes)."""
    meta = {
        "format": "torchvol-dataset",
        "version": 2,  # 2: AOVs in compressed .npz (1: float32 .npy)
        "layout": layout,
        "count": count,
        "seed": seed,
        "shard_size": shard_size if layout == "webdataset" else None,
        "aovs": list(recipe.aovs),
        "recipe": recipe.describe(),
        "conventions": CONVENTIONS,
        **({"frames": recipe.sequence.frames, "sequence": SEQUENCE_CONVENTIONS} if recipe.sequence else {}),
        **dataset_meta(recipe),
        # only where the bytes differ from the kernels'; absent otherwise: older datasets keep their meta bytes
        **({"eager": True} if compile == "off" else {}),
    }
    return json.dumps(meta, sort_keys=True, indent=1).encode() + b"\n"


def open_dataset(out: Path, meta_bytes: bytes, layout: Layout) -> None:
    """Makes `out` ready to (re)write: a new dataset's folders and meta.json, or the same dataset
    resumed (its meta.json byte-equal to `meta_bytes`, a killed run's temporaries removed); refuses
    a folder that holds something else."""
    if (out / "meta.json").is_file():
        if (out / "meta.json").read_bytes() != meta_bytes:
            fail("out", str(out), "holds a dataset made with other settings (recipe, seed, count, layout, "
                 "shard size or compile); use a new folder")
    elif out.exists() and any(out.iterdir()):
        fail("out", str(out), "exists and is not a torchvol dataset; use a new or empty folder")
    sub = out / ("samples" if layout == "folder" else "shards")
    sub.mkdir(parents=True, exist_ok=True)
    for stale in list(sub.glob(".*.tmp")) + list(out.glob(".*.tmp")):
        stale.unlink()  # temporaries of a killed run: never visible as data, removed before resuming
    atomic_write(out / "meta.json", meta_bytes)


def _execute(tasks: list[Task], *, workers: int, threads: int | None, scheduler: str | None):
    """Run `tasks`; yields the number of samples each finished task wrote, as they finish."""
    if not tasks:
        return
    if scheduler is not None:
        try:
            from distributed import Client, as_completed
        except ImportError:
            fail("scheduler", scheduler, "needs the dask distributed package (pip install distributed)")
        with Client(scheduler) as client:
            client.run(tune_process)  # each worker's heap; its wait policy where torch is not loaded there yet
            futures = client.map(run_task, tasks, pure=False)
            for future in as_completed(futures):
                yield len(future.result())
        return
    # one intra-op thread a worker unless asked: a render is thousands of small ops, and a second
    # thread gained at most 1.3x on a quiet 2-core VM but lost 4x where waking a sleeping thread is
    # slow and 3x beside a busy process; worker processes scale instead (docs/DATASETS.md, "Threads")
    threads = 1 if threads is None else threads
    if workers == 1:
        with torch_threads(threads):
            for task in tasks:
                yield len(run_task(task))
        return
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor
    from concurrent.futures import as_completed as done_order

    # one thread a worker: forked (torch and the kernels loaded already: a spawned worker spent ~3 s
    # importing torch, as long as 64 clouds take to render); a fork inherits the parent's tuning,
    # and torch's OpenMP pool, which does not survive a fork, never runs on one thread. More threads:
    # spawned, tuned by the initializer (a module without torch) before the tasks import torch
    start = "fork" if threads == 1 and "fork" in multiprocessing.get_all_start_methods() else "spawn"
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context(start),
                             initializer=init_worker, initargs=(threads,)) as pool:
        futures = [pool.submit(run_task, t) for t in tasks]
        try:
            for future in done_order(futures):
                yield len(future.result())
        finally:
            for f in futures:
                f.cancel()
