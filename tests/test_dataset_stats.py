"""`torchvol stats DIR`: the summary's numbers equal values computed directly from the files, in both
layouts; a degenerate recipe (nothing in the frame, black sky) is flagged; leading view axes and
every kind of drawn value are tolerated."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from torchvol.cli import main
from torchvol.dataset.generate import generate
from torchvol.dataset.stats import dataset_stats, image_stats, param_distributions

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "datasets" / "clouds.toml"
TINY = {"image.width": 8, "image.height": 8, "march.steps": 4}


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    base = tmp_path_factory.mktemp("stats")
    out = {}
    for layout in ("folder", "webdataset"):
        out[layout] = base / layout
        generate(RECIPE, count=4, out=out[layout], seed=1, overrides=TINY, layout=layout, shard_size=3)
    # nothing to see: a medium that does not extinguish under a black sky
    out["empty"] = base / "empty"
    generate(RECIPE, count=4, out=out["empty"], overrides={**TINY, "volumes[0].sigma_t": 0.0, "sky.radiance": [0, 0, 0]})
    return out


def direct(folder: Path) -> dict:
    """The summary's numbers computed here from the PNG and .npy files, sample by sample."""
    rows, depths = [], []
    for i in range(4):
        stem = folder / "samples" / f"{i:06d}"
        x = np.asarray(Image.open(f"{stem}.image.png"), dtype=np.float64) / 255.0  # (H, W, 3)
        a = np.asarray(Image.open(f"{stem}.alpha.png"), dtype=np.float64) / 255.0
        d = np.load(f"{stem}.depth.npy")
        hit = float((d > 0).mean())
        constant = all(x[..., c].std() < 1 / 255 for c in range(3))
        rows.append({"mean": x.mean(), "alpha": a.mean(), "hit": hit, "clipped": (x >= 1).any(-1).mean(),
                     "empty": constant or (a.mean() < 0.01 and hit < 0.01)})
        depths.append(d[d > 0])
    return {"rows": rows, "depth": np.concatenate(depths)}


def test_summary_equals_values_computed_from_the_files(data):
    stats, truth = dataset_stats(data["folder"]), direct(data["folder"])
    s = stats["summary"]
    assert (s["samples"], s["images"]) == (4, 4) and not stats["flagged"] and stats["warnings"] == []
    assert s["mean_radiance"] == pytest.approx(np.mean([r["mean"] for r in truth["rows"]]), abs=1e-6)
    assert s["alpha_coverage"] == pytest.approx(np.mean([r["alpha"] for r in truth["rows"]]), abs=1e-6)
    assert s["hit_share"] == pytest.approx(np.mean([r["hit"] for r in truth["rows"]]))
    assert s["empty_share"] == np.mean([r["empty"] for r in truth["rows"]]) == 0.0
    assert s["saturated_share"] == np.mean([r["clipped"] > 0.1 for r in truth["rows"]])
    for row, r in zip(stats["images"], truth["rows"]):
        assert row["clipped_share"] == pytest.approx(r["clipped"]) and row["hit_share"] == pytest.approx(r["hit"])
    assert s["depth"]["median"] == pytest.approx(float(np.median(truth["depth"])), rel=1e-6)
    assert (s["depth"]["min"], s["depth"]["max"]) == (truth["depth"].min(), truth["depth"].max())
    records = [json.loads(line) for line in (data["folder"] / "manifest.jsonl").read_text().splitlines()]
    params = stats["params"]
    assert params["volumes[0].sigma_t"] == {"kind": "numeric",
                                            "components": {"": [r["params"]["volumes[0].sigma_t"] for r in records]}}
    assert params["camera.eye"]["components"]["[2]"] == [r["params"]["camera.eye"][2] for r in records]
    assert params["lights"]["kind"] == "choice" and sum(params["lights"]["counts"].values()) == 4


def test_webdataset_layout_gives_the_same_statistics(data):
    folder, shards = dataset_stats(data["folder"]), dataset_stats(data["webdataset"])
    assert len(list((data["webdataset"] / "shards").glob("*.tar"))) == 2
    for key in ("summary", "images", "params", "flagged"):
        assert folder[key] == shards[key], key


def test_degenerate_recipe_is_flagged_and_strict_exits_non_zero(data, tmp_path, capsys):
    stats = dataset_stats(data["empty"])
    assert stats["flagged"] and stats["summary"]["empty_share"] == 1.0 and stats["summary"]["depth"] is None
    assert stats["warnings"] == ["empty: 100% of the 4 images are empty (more than 10%)"]
    assert main(["stats", str(data["empty"]), "--out", str(tmp_path / "plot.png")]) == 0
    out, err = capsys.readouterr()
    assert "| empty | 4 | 100.0 | 0.0 |" in out and "warning: degenerate recipe: empty: 100%" in err
    assert Image.open(tmp_path / "plot.png").size[0] > 300
    assert json.loads((data["empty"] / "stats.json").read_text())["flagged"] is True
    assert (data["empty"] / "stats.md").read_text().startswith("| recipe |")
    assert main(["stats", str(data["empty"]), "--strict", "--out", str(tmp_path / "p.png")]) == 1
    assert main(["stats", str(data["webdataset"]), "--strict"]) == 0 and (data["webdataset"] / "stats.png").is_file()
    saved = json.loads((data["webdataset"] / "stats.json").read_text())
    assert saved["summary"] == dataset_stats(data["webdataset"])["summary"] and "_depths" not in saved
    eye = saved["params"]["camera.eye"]  # numeric draws summarised: min, mean, max per component
    assert eye["kind"] == "numeric" and eye["min"]["[0]"] <= eye["mean"]["[0]"] <= eye["max"]["[0]"]
    assert main(["stats", str(data["empty"]), "--max-share", "2"]) == 2
    assert "--max-share: got 2.0; expected a share in [0, 1]" in capsys.readouterr().err
    with pytest.raises(ValueError, match="no manifest.jsonl"):
        dataset_stats(tmp_path)


def test_image_statistics_per_view_with_a_leading_axis():
    image = np.zeros((2, 3, 4, 4), np.float32)  # view 0: black; view 1: top half white
    image[1, :, :2] = 1.0
    image[1, 0, 3, 3] = 0.5
    alpha = np.zeros((2, 1, 4, 4), np.float32)
    alpha[1] = 0.5
    depth = np.zeros((2, 1, 4, 4), np.float32)
    depth[1, 0, 0] = [1.0, 2.0, np.inf, np.nan]  # only finite positive depths are hits
    v0, v1 = image_stats(image, alpha, depth)
    assert v0 == {"mean_radiance": 0.0, "alpha_coverage": 0.0, "hit_share": 0.0, "clipped_share": 0.0,
                  "constant": True, "empty": True, "saturated": False}
    assert v1["hit_share"] == 2 / 16 and v1["clipped_share"] == 0.5 and v1["alpha_coverage"] == 0.5
    assert v1["saturated"] and not v1["empty"] and not v1["constant"]
    assert not image_stats(image, alpha, depth, saturated_pixels=0.5)[1]["saturated"]


def test_samples_stored_per_view_count_each_view(data, tmp_path):
    d = tmp_path / "views"
    shutil.copytree(data["folder"], d)
    records = [json.loads(line) for line in (d / "manifest.jsonl").read_text().splitlines()]
    views = {k: [records[0]["files"][k], records[1]["files"][k]] for k in ("image", "alpha", "depth")}
    two = [{**records[0], "files": {**records[0]["files"], **views}}, *records[2:]]
    (d / "manifest.jsonl").write_text("".join(json.dumps(r) + "\n" for r in two))
    stats, flat = dataset_stats(d), dataset_stats(data["folder"])
    assert (stats["summary"]["samples"], stats["summary"]["images"]) == (3, 4)
    assert [(r["index"], r["image"]) for r in stats["images"]] == [(0, 0), (0, 1), (2, 0), (3, 0)]
    assert stats["summary"]["mean_radiance"] == pytest.approx(flat["summary"]["mean_radiance"])


def test_every_kind_of_drawn_value():
    records = [{"params": {"n": 1, "v": [1.0, 2.0], "per_view": [[0, 1], [2, 3]], "s": "hg", "mixed": 1.0, "b": True,
                           "long": list(range(6))}},
               {"params": {"n": 2.5, "v": [3.0, 4.0], "per_view": [[4, 5], [6, 7]], "s": "iso", "mixed": "x", "b": False,
                           "long": list(range(6))}}]
    p = param_distributions(records)
    assert p["n"]["components"] == {"": [1.0, 2.5]}
    assert p["v"]["components"] == {"[0]": [1.0, 3.0], "[1]": [2.0, 4.0]}
    assert p["per_view"]["components"] == {"[0]": [0.0, 2.0, 4.0, 6.0], "[1]": [1.0, 3.0, 5.0, 7.0]}
    assert p["s"] == {"kind": "choice", "counts": {"hg": 1, "iso": 1}}
    assert p["mixed"]["counts"] == {"1.0": 1, "x": 1} and p["b"]["counts"] == {"true": 1, "false": 1}
    assert len(p["long"]["components"][""]) == 12
