"""Seed 001 variants: hybrid traversal (same image, fewer steps), glow, rounded voxels, fog in the
DDA — each against a limit with a known answer."""

from __future__ import annotations

import pytest
import torch
from conftest import assert_close

import torchvol as tv

pytestmark = pytest.mark.usefixtures("one_thread")  # small ops: threads only add overhead


def test_hybrid_terrain_same_image_fewer_steps():
    a = tv.render(tv.preset("voxel-terrain", width=40, height=24, size=32))
    b = tv.render(tv.preset("voxel-terrain", width=40, height=24, size=32, traversal="hybrid"))
    assert torch.equal(a.image, b.image) and torch.equal(a.depth, b.depth)
    assert b.stats["voxel_steps"] < a.stats["voxel_steps"], (b.stats["voxel_steps"], a.stats["voxel_steps"])


def test_glow_adds_light_and_vanishes_at_zero_intensity():
    on = tv.render(tv.preset("voxel-glow", width=32, height=18))
    off = tv.render(tv.preset("voxel-glow", width=32, height=18, intensity=0.0))
    assert (on.radiance >= off.radiance).all() and (on.radiance > off.radiance).any()
    assert torch.equal(on.depth, off.depth)
    # glow colour (0.4, 0.6, 1.0): the added light has those proportions
    extra = (on.radiance - off.radiance)[0].reshape(3, -1)
    k = extra[2].argmax()
    assert_close(extra[:, k] / extra[2, k], torch.tensor([0.4, 0.6, 1.0]), atol=1e-5, what="glow colour ratio")


def wall(fog=None, rounded=None, lights=True):
    s = {
        "image": {"width": 12, "height": 10},
        "camera": {"eye": [0.0, 0.0, -5.0], "target": [0.0, 0.0, 0.0], "fov_y": 30.0},
        "lights": [{"direction": [0.3, 0.5, -1.0], "intensity": 0.5}] if lights else [],
        "voxels": {"occupancy": {"function": {"fn": lambda c: (c[:, 2] == 3).long()}},
                   "cells": {"min": [-8, -8, -2], "max": [8, 8, 4]}},
    }
    if fog is not None:
        s["voxels"]["fog"] = fog
    if rounded is not None:
        s["voxels"]["rounded"] = rounded
    return s


def test_fog_transmittance_without_sun_is_beer_lambert():
    sigma = 0.1
    clear = tv.render(wall(lights=False))
    out = tv.render(wall(fog={"density": sigma}, lights=False))
    fc = clear.camera.rays().forward_cos.reshape(10, 12)
    path = 5.0 / fc  # empty cells from the grid's entry (z = -2) to the wall (z = 3)
    expected = clear.radiance[0] * torch.exp(-sigma * path).float()
    assert_close(out.radiance[0], expected, atol=1e-5, what="fogged surface radiance")
    zero = tv.render(wall(fog={"density": 0.0}))
    assert torch.equal(zero.radiance, tv.render(wall()).radiance)


def test_fog_in_scatter_adds_sunlight():
    a = tv.render(wall(fog={"density": 0.1}, lights=False))
    b = tv.render(wall(fog={"density": 0.1}))
    c = tv.render(wall())
    assert (b.radiance > a.radiance).all() and not torch.equal(b.radiance, c.radiance)


def test_fog_light_per_distinct_cell_is_bitwise_the_per_visit_twin(monkeypatch):
    """voxels.fog traces one shadow ray per distinct visited (scene, cell); the per-visit reference
    gives the same bits: a batch of two scenes (their own densities and suns), a sun and a point
    light. Dr.Jit's walk sums the same light per distinct cell in its kernel (its exp its own:
    within float rounding)."""
    from torchvol.scene.presets import preset_dict
    from torchvol.voxel.passes.fog import FogGlow

    def scene(density, sun):
        s = preset_dict("voxel-fog", width=48, height=32, density=density)
        s["lights"][0]["direction"] = sun
        s["lights"].append({"kind": "point", "position": [2.0, 9.0, -3.0], "intensity": 20.0})
        return s

    scenes = [scene(0.04, [-0.4, 0.5, 0.6]), scene(0.1, [0.5, 0.3, -0.2])]
    fast, kernel = tv.render(scenes, compile="off"), tv.render(scenes)
    assert kernel.stats["voxel_steps"] == fast.stats["voxel_steps"]
    assert float((kernel.radiance - fast.radiance).abs().max()) < 1e-6 * float(fast.radiance.abs().max())
    calls = []
    reference = FogGlow.fog_light_reference
    monkeypatch.setattr(FogGlow, "_fog_light", lambda self, visits: calls.append(1) or reference(self, visits))
    slow = tv.render(scenes, compile="off")
    assert calls and fast.stats["voxel_steps"] == slow.stats["voxel_steps"]
    diff = (fast.radiance - slow.radiance).abs()
    assert torch.equal(fast.radiance, slow.radiance), f"largest difference {diff.max():.3g} at {diff.argmax()}"
    assert not torch.equal(fast.radiance, tv.render([tv.preset("voxel-fog", width=48, height=32, density=0.0)] * 2).radiance)


def test_rounded_voxels_zero_radius_is_the_cube_and_rounding_recedes():
    plain = tv.render(wall())
    cube = tv.render(wall(rounded={"radius_min": 0.0, "radius_range": 0.0}))
    assert torch.equal(cube.alpha, plain.alpha)
    assert_close(cube.depth, plain.depth, atol=1e-5, what="zero-radius rounded depth")
    # shaded as the cube too: its normal is the face's where the point lies on the inner box (was 0: black)
    assert_close(cube.radiance, plain.radiance, atol=1e-5, what="zero-radius rounded radiance")
    round_ = tv.render(wall(rounded={"radius_min": 0.3, "radius_range": 0.2}))
    both = (round_.alpha > 0) & (plain.alpha > 0)
    assert (round_.depth[both] >= plain.depth[both] - 1e-5).all()
    n = round_.aovs["normal"][0].reshape(3, -1)
    hit = round_.alpha[0, 0].reshape(-1) > 0
    assert_close(n[:, hit].norm(dim=0), torch.ones(int(hit.sum())), atol=1e-5, what="rounded normals are unit")
