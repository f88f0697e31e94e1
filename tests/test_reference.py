"""References: the rung ladder, its bound measured against a finer rung, climbing, the cache; the
path-traced ladder of every order of scattering."""

import importlib

import pytest
import torch

from torchvol.measure.reference import (
    BOUND_FLOOR,
    FLOAT32_MIN_TOLERANCE,
    PATH_BOUNCES,
    PATH_MAX_RUNG,
    Ladder,
    every_order_applies,
    image_error,
    rung_scene,
    rung_tolerance,
    with_every_order,
)
from torchvol.scene.presets import preset_dict
from torchvol.scene.quality import QUALITY

PUFF = preset_dict("cloud-puff", width=16, height=12)


@pytest.mark.slow
def test_each_rungs_bound_holds_against_a_finer_rung(tmp_path, one_thread):
    ladder = Ladder(PUFF, cache=tmp_path)
    finest = ladder.rung(3)["image"]
    bounds = []
    for k in (1, 2):
        ladder.k = k
        ref = ladder.reference()
        bounds.append(ref.bound)
        assert image_error(ref.image, finest)["rmse"] <= ref.bound, k  # measured ground truth: a rung finer still
    assert bounds[1] < bounds[0] / 2


def test_settle_climbs_until_the_bound_is_a_factor_under_the_error(tmp_path, one_thread):
    ladder = Ladder(PUFF, cache=tmp_path)
    first = ladder.reference()
    close = first.image + 2 * first.bound * torch.randn(first.image.shape, generator=torch.Generator().manual_seed(0))
    settled = ladder.settle([close], factor=10.0)  # an image twice the first bound away: rung 1 is not enough
    assert settled.rung > 1
    assert settled.bound * 10 <= image_error(close, settled.image)["rmse"] or settled.bound <= BOUND_FLOOR
    far = first.image + 0.3
    assert Ladder(PUFF, cache=tmp_path).settle([far], factor=10.0).rung == 1  # a large error: rung 1 suffices


def test_rungs_come_from_the_cache(tmp_path, monkeypatch, one_thread):
    Ladder(PUFF, cache=tmp_path).reference()
    rendered = []

    def render(*args, **kwargs):
        rendered.append(1)
        raise RuntimeError("rendered")

    monkeypatch.setattr(importlib.import_module("torchvol.renderer.executor"), "render", render)
    again = Ladder(PUFF, cache=tmp_path).reference()
    assert not rendered and again.rung == 1 and again.bound > 0
    with pytest.raises(RuntimeError, match="rendered"):  # another scene: another hash
        Ladder({**PUFF, "time": 1.0}, cache=tmp_path).reference()


def test_rung_scenes():
    scene, dtype = rung_scene(PUFF, 1, spp=2)
    assert scene["march"]["tolerance"] == rung_tolerance(1) and scene["march"]["min_transmittance"] == rung_tolerance(1) / 10
    assert scene["image"]["spp"] == 2 and dtype == torch.float32
    assert scene["lights"][0]["shadow"] == {"method": "march", "steps": 32}  # 384 rays: marching is cheaper
    big, _ = rung_scene(preset_dict("cloud-puff"), 1, spp=1)
    assert big["lights"][0]["shadow"] == {"method": "grid", "resolution": 192}  # 256²: the grid is
    assert rung_scene(preset_dict("cloud-puff"), 3, spp=1)[0]["lights"][0]["shadow"]["method"] == "march"  # 768: over the cap
    last = max(k for k in range(8) if rung_tolerance(k) >= FLOAT32_MIN_TOLERANCE)
    assert rung_scene(PUFF, last + 1, spp=1)[1] == torch.float64 and rung_scene(PUFF, last, spp=1)[1] == torch.float32
    template, _ = rung_scene(preset_dict("template-clouds", width=16, height=12), 2, spp=1)
    assert "tolerance" not in template["march"] and template["march"]["steps"] == 80  # the alpha look's own sampling
    assert template["march"]["placement"] == "adaptive" and template["march"]["dither"] == "sin"
    assert "lod" not in template["march"] and "density_threshold" not in template["march"]
    terrain, _ = rung_scene(preset_dict("voxel-terrain", width=16, height=12), 2, spp=1)
    assert terrain["voxels"]["max_steps"] == 4 * QUALITY["reference"].voxel_max_steps
    assert terrain["voxels"]["shadow"]["steps"] == 4 * QUALITY["reference"].voxel_shadow_steps


def test_a_path_traced_ladder_bounds_its_noise(tmp_path, one_thread):
    """Every order of scattering, path-traced: rung k has 4^k times rung 0's paths a pixel, so its
    noise, estimated from rungs k − 1 and k, bounds its distance to a rung with 16× more paths (its
    noise a quarter of rung k's: the distance is rung k's own noise, within 3%), and not loosely."""
    ladder = Ladder(with_every_order(PUFF), spp=2, cache=tmp_path)
    assert ladder.traced and ladder.max_rung == PATH_MAX_RUNG
    ref, finest = ladder.reference(), ladder.rung(3)["image"]
    distance = image_error(ref.image, finest)["rmse"]
    assert ref.dtype == "float32" and distance <= ref.bound <= 3.0 * distance, (distance, ref.bound)
    scene, _ = rung_scene(with_every_order(PUFF), 2, spp=2)
    assert scene["path"] == {"bounces": PATH_BOUNCES, "samples": 8 * 16, "single": "paths"}  # 16 paths a pixel on rung 0, 4× a rung


def test_which_scenes_get_an_every_order_reference():
    assert every_order_applies(PUFF)  # octaves: an approximation of the orders past the first
    single = {**PUFF, "volumes": [{k: v for k, v in PUFF["volumes"][0].items() if k != "multiple_scattering"}]}
    assert not every_order_applies(single) and every_order_applies(single, "always")
    assert not every_order_applies(PUFF, "never")
    assert every_order_applies(preset_dict("voxel-terrain", width=8, height=8), "always")  # Lambert voxel faces
    assert not every_order_applies(preset_dict("voxel-water", width=8, height=8), "always")  # paths cannot trace water
    assert every_order_applies(preset_dict("terrain-clouds", width=8, height=8))  # octaves over a terrain paths trace
    assert not every_order_applies(with_every_order(PUFF), "always")  # already path-traced
