"""Loading where users load: webdataset shards through the `webdataset` package and through Hugging
Face `datasets`' webdataset loader give every label with the shape and dtype docs/DATASETS.md states
and FolderDataset's values; the label table there names every AOV."""

import re
from pathlib import Path

import numpy as np
import pytest
import torch

import torchvol as tv
from torchvol.dataset.generate import generate
from torchvol.renderer.aovs import AOVS

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "datasets" / "clouds.toml"
TINY = {"image.width": 8, "image.height": 6, "march.steps": 4}
H, W = 6, 8


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    base = tmp_path_factory.mktemp("loaders")
    for layout in ("folder", "webdataset"):
        generate(RECIPE, count=3, out=base / layout, seed=2, overrides=TINY, layout=layout, shard_size=2)
    return {"folder": tv.FolderDataset(base / "folder"),
            "shards": [str(p) for p in sorted((base / "webdataset" / "shards").glob("shard-*.tar"))]}


def check_folder_item(item: dict) -> None:
    assert item["image"].shape == (3, H, W) and item["image"].dtype == torch.float32
    for key in ("depth", "alpha", "depth_median"):
        assert item[key].shape == (1, H, W) and item[key].dtype == torch.float32, key
    assert item["K"].shape == (3, 3) and item["world_to_camera"].shape == (4, 4)
    assert item["K"].dtype == item["world_to_camera"].dtype == torch.float32


def test_webdataset_package_decodes_the_folder_values(data):
    wds = pytest.importorskip("webdataset")
    samples = list(wds.WebDataset(data["shards"], shardshuffle=False).decode("torchrgb"))
    assert [s["json"]["index"] for s in samples] == [0, 1, 2]
    for s in samples:
        ref = data["folder"][s["json"]["index"]]
        check_folder_item(ref)
        assert s["image.png"].shape == (3, H, W) and s["image.png"].dtype == torch.float32
        assert torch.equal(s["image.png"], ref["image"])
        assert torch.equal(s["alpha.png"][:1], ref["alpha"])  # decoded as RGB: one channel
        assert s["depth.npy"].shape == (H, W) and s["depth.npy"].dtype == np.float32
        assert torch.equal(torch.from_numpy(s["depth.npy"])[None], ref["depth"])
        assert torch.equal(torch.from_numpy(s["depth_median.npz"]["depth_median"]), ref["depth_median"])
        assert torch.equal(torch.tensor(s["json"]["K"], dtype=torch.float32), ref["K"])
        assert torch.equal(torch.tensor(s["json"]["world_to_camera"], dtype=torch.float32), ref["world_to_camera"])
        assert (s["json"]["seed"], s["json"]["params"]) == (ref["seed"], ref["params"])


def test_hugging_face_datasets_webdataset_loader_decodes_the_folder_values(data, tmp_path):
    datasets = pytest.importorskip("datasets")
    ds = datasets.load_dataset("webdataset", data_files={"train": data["shards"]}, split="train",
                               cache_dir=str(tmp_path)).with_format("torch")
    assert len(ds) == 3
    for s in ds:
        ref = data["folder"][int(s["json"]["index"])]
        image, alpha = s["image.png"], s["alpha.png"]
        assert image.shape == (3, H, W) and image.dtype == torch.uint8
        assert alpha.shape == (1, H, W) and alpha.dtype == torch.uint8
        assert torch.equal(image.float() / 255, ref["image"]) and torch.equal(alpha.float() / 255, ref["alpha"])
        assert s["depth.npy"].shape == (H, W) and s["depth.npy"].dtype == torch.float32
        assert torch.equal(s["depth.npy"][None], ref["depth"])
        assert torch.equal(s["depth_median.npz"]["depth_median"], ref["depth_median"])
        assert s["json"]["K"].dtype == s["json"]["world_to_camera"].dtype == torch.float32
        assert torch.equal(s["json"]["K"], ref["K"]) and torch.equal(s["json"]["world_to_camera"], ref["world_to_camera"])
        assert int(s["json"]["seed"]) == ref["seed"]
        assert s["json"]["params"]["volumes[0].sigma_t"] == pytest.approx(ref["params"]["volumes[0].sigma_t"])


def test_label_table_names_every_label_and_aov():
    text = (ROOT / "docs" / "DATASETS.md").read_text()
    start = text.index("| label |")
    rows = [line for line in text[start:].splitlines() if line.startswith("|")]
    labels = {m.group(1) for line in rows[2:] if (m := re.match(r"\|\s*`(\w+)`", line))}
    assert {"image", "depth", "alpha", "K", "world_to_camera", "index", "seed", "params"} <= labels
    assert {k.name for k in AOVS} <= labels, "docs/DATASETS.md's label table lacks a row for an AOV"
