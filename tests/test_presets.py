"""Every bundled preset: the normative names exist, each renders at odd sizes without NaN, and its
stats hold only the passes it calls for (each ran, each took time, none outside its plan)."""

from __future__ import annotations

import pytest
import torch

import torchvol as tv
from torchvol.renderer.plan import make_plan

# DESIGN.md's normative preset names
NORMATIVE = ["template-clouds", "cloud-puff", "homogeneous-box", "voxel-carved-box", "voxel-terrain", "voxel-fog",
             "voxel-glow", "voxel-rounded", "explosion", "fire", "atmosphere", "cloudscape", "fur-ball",
             "terrain-clouds", "multi-layer", "particles", "god-rays",
             "voxel-pbr", "voxel-water", "voxel-gi"]


def test_the_normative_presets_exist():
    missing = sorted(set(NORMATIVE) - set(tv.preset_names()))
    assert not missing, f"presets missing: {missing}"


@pytest.mark.parametrize("name", tv.preset_names())
def test_renders_at_odd_sizes_without_nan_and_runs_only_its_plan(name, one_thread):
    for width, height in ((7, 5), (1, 3)):
        scene = tv.preset(name, width=width, height=height)
        out = tv.render(scene)
        assert out.image.shape == (1, 3, height, width), name
        for key, value in {"image": out.image, "radiance": out.radiance, "depth": out.depth, "alpha": out.alpha,
                           **out.aovs}.items():
            assert torch.isfinite(value).all(), f"{name} at {width}×{height}: non-finite {key}"
        assert float(out.image.min()) >= 0.0 and float(out.image.max()) <= 1.0
        planned = make_plan(scene).names()
        ran = out.stats["passes"]
        assert set(ran) <= set(planned), f"{name}: ran passes outside the plan: {sorted(set(ran) - set(planned))}"
        assert all(out.stats["time_s"][p] > 0 for p in ran), f"{name}: a pass that ran took no time: {out.stats['time_s']}"
