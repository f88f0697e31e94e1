"""The voxel shading kernels (`voxel.shade_kernel`) against the eager shading functions they trace
(`voxel.shade`): the same lanes functions, Dr.Jit's exp and log within float rounding."""

import math

import numpy as np
import pytest
import torch

import torchvol as tv
from tests.conftest import assert_close
from torchvol.runtime.compilation import drjit_available
from torchvol.voxel.cone import build_mips, mip_table, trace_cones
from torchvol.voxel.passes import shading
from torchvol.voxel.shade import voxel_ao
from torchvol.voxel.shade_kernel import ao_kernel, cones_kernel, mips_lanes
from torchvol.voxel.walk import int_table


@pytest.mark.skipif(not drjit_available(), reason="Dr.Jit's LLVM backend is not available")
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_ao_kernel_is_the_eager_ao(seed):
    """Hits on every face of random cells of two scenes with their own cell ranges, border cells
    included (their neighbours outside the range are empty), any UV and gamma."""
    g = torch.Generator().manual_seed(seed)
    Z, Y, X = 6, 7, 8
    occ = ((torch.rand(2, Z, Y, X, generator=g) < 0.4) * torch.randint(1, 4, (2, Z, Y, X), generator=g)).to(torch.uint8)
    lo = torch.randint(-4, 4, (2, 3), generator=g)
    hi = lo + torch.tensor([X, Y, Z])
    n = 4000
    s = torch.randint(0, 2, (n,), generator=g)
    cell = lo[s] + (torch.rand(n, 3, generator=g) * (hi - lo)[s]).long()
    axis = torch.randint(0, 3, (n,), generator=g)
    normal = torch.zeros(n, 3).scatter_(1, axis[:, None], torch.randint(0, 2, (n, 1), generator=g).float() * 2 - 1)
    uv, gamma = torch.rand(n, 2, generator=g), 0.3 + 1.7 * torch.rand(n, generator=g)
    flat = occ.reshape(-1)
    base = ((s * Z - lo[s, 2]) * Y - lo[s, 1]) * X - lo[s, 0]

    def lookup(c):
        r, ss = c - lo[s], s
        inside = ((c >= lo[ss]) & (c < hi[ss])).all(dim=1)
        r = torch.where(inside[:, None], r, 0)
        return inside & (flat[((ss * Z + r[:, 2]) * Y + r[:, 1]) * X + r[:, 0]] > 0)

    eager = voxel_ao(lookup, cell, normal, axis, uv, gamma=gamma)
    kernel = ao_kernel(int_table(flat), base, torch.tensor([Y, X]), lo[s], hi[s], cell, normal, axis, uv, gamma)
    assert (eager < 0.5).any() and (eager == 1).any(), "no hit was occluded, or every one was"
    assert_close(kernel, eager, atol=1e-6, what="AO")
    # each hit's range and base gathered from its scene's inside the kernel (the tracer's way): the same bits
    bases = ((torch.arange(len(lo)) * Z - lo[:, 2]) * Y - lo[:, 1]) * X - lo[:, 0]
    by_scene = ao_kernel(int_table(flat), bases, torch.tensor([Y, X]), lo, hi, cell, normal, axis, uv, gamma, scene=s)
    assert torch.equal(by_scene, kernel), f"{int((by_scene != kernel).sum())} hits differ"


@pytest.mark.skipif(not drjit_available(), reason="Dr.Jit's LLVM backend is not available")
@pytest.mark.parametrize("seed, aperture", [(0, 20.0), (1, 60.0)])
def test_the_cones_kernel_is_the_eager_cone_march(seed, aperture):
    """Cones from random points of two scenes' random mip chains (8³: four levels), in any
    direction, narrow and wide (every level blended), some starting outside the cube or
    limited by max_t: the same `cone_step`, in one Dr.Jit loop."""
    g = torch.Generator().manual_seed(seed)
    occ = (torch.rand(2, 8, 8, 6, generator=g) < 0.25).float()
    levels = build_mips(occ, torch.rand(2, 3, 8, 8, 6, generator=g), occ * (torch.rand(2, 8, 8, 6, generator=g) < 0.7))
    n = 3000
    origin = torch.rand(n, 3, generator=g) * 10.0 - 1.0
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=1)
    s = torch.randint(0, 2, (n,), generator=g)
    ratio = torch.full((n,), 2.0 * math.tan(math.radians(aperture)))
    max_t = torch.rand(n, generator=g) * 12.0
    colour, occlusion = trace_cones(levels, origin, d, s, ratio, steps=24, max_t=max_t)
    k_colour, k_occlusion = cones_kernel(mips_lanes(*mip_table(levels)), origin, d, s, ratio, steps=24, max_t=max_t)
    assert (occlusion > 0.5).any() and (occlusion == 0).any(), "no cone was occluded, or every one was"
    assert_close(k_occlusion, occlusion, atol=1e-6, what="occlusion")
    assert_close(k_colour, colour, atol=1e-6 * float(colour.abs().max()), what="radiance")


@pytest.mark.skipif(not drjit_available(), reason="Dr.Jit's LLVM backend is not available")
def test_the_cone_preset_renders_as_its_eager_reference():
    scene = tv.preset("voxel-cone", width=24, height=18)
    eager, kernel = tv.render(scene, compile="off"), tv.render(scene)
    assert_close(kernel.radiance, eager.radiance, atol=1e-6 * float(eager.radiance.abs().max()), what="radiance")
    for key, value in eager.aovs.items():
        assert_close(kernel.aovs[key], value, atol=1e-6, what=key)


def fused_calls(monkeypatch) -> list:
    """A list that grows by one each time `Shading.shade` runs its fused kernel."""
    calls, kernel_call = [], shading.Shading._kernel
    monkeypatch.setattr(shading.Shading, "_kernel",
                        lambda self, *a, lit, **k: (lit and calls.append(1)) or kernel_call(self, *a, lit=lit, **k))
    return calls


def _lit_scene(seed: int, *, rounded: bool) -> dict:
    """A voxel scene of every marched-look effect the fused shading kernel takes: a textured
    Lambert material, a GGX and an emissive one, AO, a shadowed sun and a shadowed point light,
    mirror reflections; `rounded`: rounded voxels (their shadow rays leave the cell first)."""
    rng = np.random.default_rng(seed)
    grid = np.zeros((12, 10, 12), dtype=np.uint8)  # (z, y, x) from cell (-6, -4, -6)
    grid[:, :2] = 1  # a textured floor
    grid[3:9, 2:2 + int(rng.integers(3, 7)), 3:9] = rng.choice([1, 2, 3], size=(6, 1, 6))  # GGX, emissive and textured towers
    return {"image": {"width": 40, "height": 32},
            "camera": {"eye": [float(rng.uniform(-9, 9)), 7.0, -10.0], "target": [0.0, 0.0, 0.0], "fov_y": 55.0},
            "sky": {"kind": "constant", "radiance": [0.2, 0.3, 0.4]},
            "lights": [{"kind": "sun", "direction": [0.3, 1.0, float(rng.uniform(-0.5, 0.5))], "intensity": 0.8,
                        "shadow": {"steps": 24}},
                       {"kind": "point", "position": [2.0, 6.0, -2.0], "intensity": 30.0, "shadow": {"steps": 24}}],
            "voxels": {"occupancy": {"grid": {"data": grid}}, "cells": {"min": [-6, -4, -6]}, "max_steps": 64,
                       "materials": [[0.8, 0.7, 0.6], {"color": [0.6, 0.6, 0.7], "roughness": float(rng.uniform(0.1, 0.5)),
                                                       "metallic": 0.5},
                                     {"color": [0.3, 0.3, 0.3], "emission": [0.4, 0.2, 0.1]}],
                       "texture": {"atlas": (rng.random((16, 16, 3)) * 255).astype(np.uint8), "tiles": 2},
                       "ambient": [0.2, 0.2, 0.25], "ao": {"gamma": float(rng.uniform(0.3, 0.8))},
                       "shadow": {"steps": 24, "offset": 0.01}, "reflections": {"bounces": 2, "steps": 32},
                       **({"rounded": {"radius_min": 0.05, "radius_range": 0.3, "steps": 6, "threshold": 0.025}}
                          if rounded else {})}}


@pytest.mark.skipif(not drjit_available(), reason="Dr.Jit's LLVM backend is not available")
@pytest.mark.parametrize("rounded", [False, True], ids=["cubes", "rounded"])
def test_the_fused_shading_kernel_is_the_shading_piece_by_piece(monkeypatch, rounded):
    """Two scenes in one batch shaded as one Dr.Jit kernel (point, AO, each light's shadow walk,
    Lambert and GGX, emission; the reflections' hits too) agree with the same lanes run piece by
    piece around the tracer's kernels (`look.fusable` off), every AOV included, and with the eager
    reference, within the tolerance table: the pieces take a point light's direction in torch (its
    float32 sqrt not correctly rounded: 3 and 5 values of 7,680 apart, by 1.2e-7, when measured)."""
    scenes = [_lit_scene(seed, rounded=rounded) for seed in (3, 4)]
    aovs = ["normal", "uv", "material", "ao", "shadow", "roughness", "metallic"]
    calls = fused_calls(monkeypatch)
    fused = tv.render(scenes, aovs=aovs)
    assert calls, "the fused kernel did not run"
    monkeypatch.setattr(shading, "fusable", lambda plan, lights: False)
    pieces = tv.render(scenes, aovs=aovs)
    for key in ["radiance", "depth"] + aovs:
        a, b = (fused.radiance, pieces.radiance) if key == "radiance" else (getattr(fused, key, None), getattr(pieces, key, None))
        if a is None:
            a, b = fused.aovs[key], pieces.aovs[key]
        assert_close(a, b, what=f"{key}: fused against piece by piece")
    assert float(fused.aovs["shadow"].min()) == 0.0 and float(fused.aovs["ao"].min()) < 0.9, "nothing shadowed or occluded"
    eager = tv.render(scenes, aovs=aovs, compile="off")
    assert_close(fused.radiance, eager.radiance, atol=1e-5, what="fused kernel against eager")


@pytest.mark.skipif(not drjit_available(), reason="Dr.Jit's LLVM backend is not available")
@pytest.mark.parametrize("density", [{"constant": 0.3}, {"fbm": {"frequency": 0.5}}], ids=["closed form", "fbm"])
def test_shadow_rays_through_volumes_are_fused_with_their_evaluations(monkeypatch, density):
    """A shadow ray that also crosses a volume beside the voxels takes the volume's lanes inside the
    fused kernel (`kernel_march.surface_lanes_of`), only where the voxels let the light through:
    the pieces' image within the tolerance table, their density evaluations and passes exactly."""
    calls = fused_calls(monkeypatch)
    scene = _lit_scene(0, rounded=False)
    scene["volumes"] = [{"density": density, "bounds": {"box": {"min": [-7, 3, -7], "max": [7, 9, 7]}}, "sigma_t": 0.8}]
    scene["march"] = {"quality": "draft"}  # (the volume's own march is eager beside voxels: few steps)
    fused = tv.render(scene)
    assert calls, "a shadow ray through a volume was not shaded in the fused kernel"
    monkeypatch.setattr(shading, "fusable", lambda plan, lights: False)
    pieces = tv.render(scene)
    assert_close(fused.radiance, pieces.radiance, what="fused against piece by piece")
    assert fused.stats["density_evals"] == pieces.stats["density_evals"] > 0
    assert fused.stats["passes"] == pieces.stats["passes"]


@pytest.mark.skipif(not drjit_available(), reason="Dr.Jit's LLVM backend is not available")
def test_gi_keeps_the_pieces(monkeypatch):
    """GI's light replaces the ambient before the direct light: its hits are shaded piece by piece."""
    calls = fused_calls(monkeypatch)
    scene = _lit_scene(0, rounded=False)
    tv.render({**scene, "voxels": {**scene["voxels"], "gi": {"method": "path", "samples": 1, "bounces": 1}}})
    assert not calls, "a GI scene was shaded in the fused kernel"
    tv.render(scene)
    assert calls
