"""SceneDataset: the same samples in any process, worker, order or batch; epochs (the README's training
example runs in tests/test_docs.py)."""

from pathlib import Path

import torch

import torchvol as tv
from torchvol.dataset.datasets import collate

ROOT = Path(__file__).resolve().parents[1]
TINY = {"image.width": 16, "image.height": 12, "march.steps": 4}
KEYS = {"image", "depth", "alpha", "K", "world_to_camera", "index", "seed", "params", "depth_median"}


def dataset(**kw):
    return tv.SceneDataset(ROOT / "datasets" / "clouds.toml", 4, overrides=TINY, **kw)


def same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(
        torch.equal(a[k], b[k]) if isinstance(a[k], torch.Tensor) else a[k] == b[k] for k in a)


def test_items_have_the_documented_keys_and_shapes():
    item = dataset()[1]
    assert set(item) == KEYS
    assert item["image"].shape == (3, 12, 16) and item["image"].dtype == torch.float32
    assert item["depth"].shape == item["alpha"].shape == item["depth_median"].shape == (1, 12, 16)
    assert item["K"].shape == (3, 3) and item["world_to_camera"].shape == (4, 4)
    assert item["index"] == 1 and item["seed"] == 0 and "volumes[0].sigma_t" in item["params"]


def test_order_and_batch_do_not_change_samples():
    ds = dataset()
    backwards = {i: ds[i] for i in reversed(range(4))}
    assert all(same(ds[i], backwards[i]) for i in range(4))
    batched = ds.batch([2, 0, 3])
    assert all(same(item, backwards[i]) for item, i in zip(batched, [2, 0, 3]))
    assert same(ds[-1], backwards[3])


def test_dataloader_workers_equal_the_main_process_loop():
    ds = dataset()
    loop = collate([ds[i] for i in range(4)])
    loader = torch.utils.data.DataLoader(ds, batch_size=2, num_workers=2, collate_fn=collate)
    batches = list(loader)
    for key in ("image", "depth", "alpha", "K", "world_to_camera", "depth_median", "index", "seed"):
        assert torch.equal(torch.cat([b[key] for b in batches]), loop[key]), key
    assert [p for b in batches for p in b["params"]] == loop["params"]


def test_epoch_draws_fresh_samples_deterministically():
    base, e0, e1 = dataset(), dataset(epoch=0), dataset(epoch=1)
    assert base[0]["params"] != e0[0]["params"] != e1[0]["params"]
    assert same(e1[0], dataset(epoch=1)[0])


def test_bad_arguments():
    import pytest

    with pytest.raises(ValueError, match="length"):
        tv.SceneDataset(ROOT / "datasets" / "clouds.toml", -1)
    with pytest.raises(IndexError):
        dataset()[4]


def test_voxel_terrain_recipe_gives_surface_labels():
    tiny = {"image.width": 16, "image.height": 12, "voxels.cells": {"min": [-8, -4, -8], "max": [8, 8, 8]},
            "march.steps": 4, "voxels.shadow.steps": 8, "voxels.fog.shadow_steps": 2}
    ds = tv.SceneDataset(ROOT / "datasets" / "voxel-terrain.toml", 2, overrides=tiny, seed=3)
    item = ds[1]
    for key, channels in {"normal": 3, "material": 1, "ao": 1, "shadow": 1, "uv": 2}.items():
        assert item[key].shape == (channels, 12, 16), key
    hit = item["alpha"][0] > 0.99
    assert hit.any() and (item["depth"][0][hit] > 0).all()
    assert torch.equal(item["image"], ds[1]["image"])  # deterministic per (seed, index)
    assert "voxels.occupancy.terrain.seed" in item["params"]
