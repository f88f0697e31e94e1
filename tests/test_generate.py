"""`torchvol generate`: layouts, read-back, determinism across workers, kill + resume byte-identical."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

import torchvol as tv
from torchvol.cli import main
from torchvol.dataset.generate import AUTO_BATCH_RAYS, auto_batch, generate
from torchvol.dataset.recipe import Recipe

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "datasets" / "clouds.toml"
TINY = {"image.width": 16, "image.height": 12, "march.steps": 4}


def tree(path: Path) -> dict[str, bytes]:
    """Every file under `path` (hidden temporaries included) by relative path."""
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted run of each layout."""
    out = {}
    for layout in ("folder", "webdataset"):
        d = tmp_path_factory.mktemp(layout) / "ds"
        report = generate(RECIPE, count=5, out=d, seed=3, overrides=TINY, layout=layout, batch=2, shard_size=2)
        assert report == {"written": 5, "count": 5, "out": str(d), "finished": True}
        out[layout] = d
    return out


def test_folder_layout_and_manifest(reference):
    d = reference["folder"]
    records = [json.loads(line) for line in (d / "manifest.jsonl").read_text().splitlines()]
    assert [r["index"] for r in records] == list(range(5)) and all(r["seed"] == 3 for r in records)
    assert set(records[0]["files"]) == {"image", "depth", "alpha", "depth_median"}
    assert all((d / f).is_file() for r in records for f in r["files"].values())
    assert "volumes[0].sigma_t" in records[0]["params"] and len(records[0]["K"]) == 3
    meta = json.loads((d / "meta.json").read_text())
    assert meta["layout"] == "folder" and meta["count"] == 5 and "planar z" in meta["conventions"]["depth"]
    assert "x right, y down, z forward" in meta["conventions"]["camera"]
    assert not [p for p in d.rglob(".*")]


def test_folder_reads_back_equal_to_the_scene_dataset(reference):
    folder = tv.FolderDataset(reference["folder"])
    live = tv.SceneDataset(RECIPE, 5, seed=3, overrides=TINY)
    assert len(folder) == 5
    for i in (0, 4):
        a, b = folder[i], live[i]
        assert a.keys() == b.keys()
        for key in ("depth", "depth_median", "K", "world_to_camera"):
            assert torch.equal(a[key], b[key]), key
        for key in ("image", "alpha"):  # 8-bit PNG
            assert a[key].shape == b[key].shape and (a[key] - b[key]).abs().max() <= 0.5 / 255 + 1e-6, key
        assert (a["index"], a["seed"], a["params"]) == (b["index"], b["seed"], b["params"])


@pytest.mark.parametrize("layout", ["folder", "webdataset"])
def test_kill_and_resume_is_byte_identical(reference, tmp_path, layout):
    d = tmp_path / "ds"
    kw = dict(count=5, out=d, seed=3, overrides=TINY, layout=layout, batch=2, shard_size=2)
    partial = generate(RECIPE, stop_after=1, **kw)  # "killed" after its first task
    assert not partial["finished"] and not (d / "manifest.jsonl").exists()
    done = tree(d)
    sub = d / ("samples" if layout == "folder" else "shards")
    (sub / ".leftover.tar.123.tmp").write_bytes(b"partial")  # a temporary the kill left behind
    finished = generate(RECIPE, **kw)
    assert finished["finished"] and finished["written"] == 5 - partial["written"]
    after = tree(d)
    assert after == tree(reference[layout])
    assert all(after[k] == v for k, v in done.items())  # finished samples untouched


def test_lost_sample_is_redone_identically(reference, tmp_path):
    d = tmp_path / "ds"
    kw = dict(count=5, out=d, seed=3, overrides=TINY, batch=2)
    generate(RECIPE, **kw)
    (d / "samples" / "000003.json").unlink()  # killed between its files and its record
    (d / "samples" / "000003.image.png").unlink()
    assert generate(RECIPE, **kw)["written"] == 1
    assert tree(d) == tree(reference["folder"])


def test_other_settings_in_an_existing_folder_are_refused(reference):
    with pytest.raises(ValueError, match="^out: "):
        generate(RECIPE, count=5, out=reference["folder"], seed=4, overrides=TINY, batch=2)
    with pytest.raises(ValueError, match="compile"):  # eager samples are not bitwise the kernels': no mixing
        generate(RECIPE, count=5, out=reference["folder"], seed=3, overrides=TINY, batch=2, compile="off")


def test_workers_give_the_same_bytes(reference, tmp_path):
    d = tmp_path / "ds"
    generate(RECIPE, count=5, out=d, seed=3, overrides=TINY, batch=2, workers=2, threads=1)
    assert tree(d) == tree(reference["folder"])


def test_the_default_batch_fills_its_rays_and_gives_the_same_bytes(reference, tmp_path):
    recipe = Recipe.load(RECIPE, TINY)  # 16×12: 192 rays a sample
    assert auto_batch(recipe, count=5, workers=1, seed=3) == 3  # two tasks a worker: ceil(5 / 2)
    # 341 samples fill the rays: 30 batches (even: as many a worker) of 334
    assert AUTO_BATCH_RAYS // 192 == 341 and auto_batch(recipe, count=10_000, workers=2, seed=3) == 334
    assert auto_batch(recipe, count=64, workers=2, seed=3) == 16  # four batches: two a worker
    big = Recipe.load(RECIPE, {"image.width": 512, "image.height": 512})
    assert auto_batch(big, count=10_000, workers=2, seed=3) == 1  # more rays than a batch holds: one sample
    d = tmp_path / "ds"
    generate(RECIPE, count=5, out=d, seed=3, overrides=TINY)
    assert tree(d) == tree(reference["folder"])


def test_dask_cluster_gives_the_same_bytes(reference, tmp_path):
    distributed = pytest.importorskip("distributed")
    d = tmp_path / "ds"
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cluster:
        generate(RECIPE, count=5, out=d, seed=3, overrides=TINY, layout="webdataset", batch=2, shard_size=2,
                 scheduler=cluster.scheduler_address)
    assert tree(d) == tree(reference["webdataset"])


def test_webdataset_shards_read_back_with_webdataset(reference):
    wds = pytest.importorskip("webdataset")
    d = reference["webdataset"]
    urls = [str(p) for p in sorted((d / "shards").glob("shard-*.tar"))]
    assert len(urls) == 3
    live = tv.SceneDataset(RECIPE, 5, seed=3, overrides=TINY)
    samples = list(wds.WebDataset(urls, shardshuffle=False).decode("torchrgb"))
    assert [s["__key__"] for s in samples] == [f"{i:06d}" for i in range(5)]
    for s in samples[:2]:
        item = live[s["json"]["index"]]
        assert torch.equal(torch.from_numpy(s["depth.npy"])[None], item["depth"])
        assert (s["image.png"] - item["image"]).abs().max() <= 0.5 / 255 + 1e-6
        assert (s["alpha.png"][:1] - item["alpha"]).abs().max() <= 0.5 / 255 + 1e-6
        assert s["json"]["params"] == item["params"] and torch.equal(torch.tensor(s["json"]["K"]), item["K"])


def test_cli_generate_and_errors(tmp_path, capsys):
    sets = [a for k, v in TINY.items() for a in ("--set", f"{k}={v}")]
    assert main(["generate", str(RECIPE), "--count", "2", "--out", str(tmp_path / "d"), *sets]) == 0
    assert json.loads(capsys.readouterr().out)["finished"] is True
    assert len(tv.FolderDataset(tmp_path / "d")) == 2
    code = main(["generate", str(RECIPE), "--count", "2", "--out", str(tmp_path / "e"),
                 "--set", "volumes[0].sigma_t={uniform=[-1,2]}"])
    err = capsys.readouterr().err
    assert code == 2 and "volumes[0].sigma_t" in err and err.count("\n") == 1
    assert main(["generate", str(RECIPE), "--count", "0", "--out", str(tmp_path / "f")]) == 2
    assert "--count: got 0" in capsys.readouterr().err  # the command line names its flag


def test_api_names_bad_arguments_by_parameter(tmp_path):
    for kw, name in (({"count": 0}, "count"), ({"count": 1, "shard_size": 0}, "shard_size"), ({"count": 1, "layout": "zip"}, "layout")):
        with pytest.raises(ValueError, match=f"^{name}: got "):
            generate(RECIPE, out=tmp_path / "g", **kw)


def test_progress_is_shown_as_lines_when_stderr_is_not_a_terminal(tmp_path, capsys):
    sets = [a for k, v in TINY.items() for a in ("--set", f"{k}={v}")]
    assert main(["generate", str(RECIPE), "--count", "2", "--out", str(tmp_path / "d"), *sets]) == 0
    err = capsys.readouterr().err
    assert "generate d" in err and "2/2" in err and "\r" not in err
    assert main(["generate", str(RECIPE), "--count", "2", "--out", str(tmp_path / "e"), *sets, "--no-progress"]) == 0
    assert capsys.readouterr().err == ""


def test_voxel_labels_are_stored_compactly_and_read_back(tmp_path):
    recipe = ROOT / "datasets" / "voxel-terrain.toml"
    tiny = {"image.width": 16, "image.height": 12, "voxels.cells": {"min": [-8, -4, -8], "max": [8, 8, 8]},
            "voxels.fog.shadow_steps": 2, "voxels.shadow.steps": 8, "march.steps": 4}
    generate(recipe, count=2, out=tmp_path / "ds", overrides=tiny, batch=2)
    folder, live = tv.FolderDataset(tmp_path / "ds"), tv.SceneDataset(recipe, 2, overrides=tiny)
    record = json.loads((tmp_path / "ds" / "manifest.jsonl").read_text().splitlines()[1])
    assert {k: Path(v).name.split(".", 1)[1] for k, v in record["files"].items() if k not in ("image", "depth", "alpha")} == {
        "normal": "normal.npz", "material": "material.npz", "ao": "ao.npz", "shadow": "shadow.npz", "uv": "uv.npz"}
    for i in range(2):
        a, b = folder[i], live[i]
        for key in ("depth", "normal", "material", "ao", "shadow"):  # lossless
            assert a[key].dtype == torch.float32 and torch.equal(a[key], b[key]), key
        assert (a["uv"] - b["uv"]).abs().max() <= 2.0**-12  # float16: within 2.4e-4 of a face
    with np.load(tmp_path / "ds" / record["files"]["material"]) as stored:
        assert stored["material"].dtype.name == "uint8"
