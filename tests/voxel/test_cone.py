"""`voxels.gi = { method = "cone", ... }`: voxel cone tracing against the furnace's e·(1 + a), the open
sky, and the path tracer (bounces = 1) on the voxel-cone preset, each within the bound measured and
stated here (cones are an approximation); the mip chain's mean property; distance LOD; hard cases
and the plan."""

from __future__ import annotations

import pytest
import torch
from test_gi import room

import torchvol as tv
from torchvol.renderer.plan import make_plan
from torchvol.scene.presets import preset_dict
from torchvol.voxel.cone import build_mips, cone_directions, default_aperture

CONE_PASSES = ["voxels.gi.mips", "voxels.gi.cones"]


def cavity(a: float, e, *, gi=None, size=(8, 8)) -> dict:
    """A room carved out of a block that fills its 16³ grid (thick walls), the camera inside."""
    inner = {"box": {"center": [0.0, 0.0, 0.0], "half_size": [3.0, 2.0, 3.0]}}
    solid = {"box": {"center": [0.0, 0.0, 0.0], "half_size": [50.0, 50.0, 50.0]}}
    scene = room([{"color": [a] * 3, "emission": e}], gi=gi or {"method": "cone"}, size=size)
    scene["voxels"].update(occupancy={"sdf": {"shape": {"subtraction": {"a": solid, "b": inner}}, "material": 1}},
                           cells={"min": [-8, -8, -8], "max": [8, 8, 8]})
    return scene


def floor(gi: dict, *, size=(8, 8), eye=(0.0, 6.0, -6.0)) -> dict:
    """A one-voxel floor under a constant sky of 1, no lights: a path sees the sky over the whole
    hemisphere, so the floor shows albedo · sky."""
    return {"image": {"width": size[0], "height": size[1]}, "sky": {"kind": "constant", "radiance": [1.0, 1.0, 1.0]},
            "camera": {"eye": list(eye), "target": [0.0, 0.0, 0.0], "fov_y": 40.0},
            "voxels": {"occupancy": {"sdf": {"shape": {"box": {"center": [0.0, -0.5, 0.0], "half_size": [8.0, 0.5, 8.0]}},
                                             "material": 1}},
                       "cells": {"min": [-8, -1, -8], "max": [8, 8, 8]}, "materials": [[0.5, 0.5, 0.5]],
                       "ambient": [0.0, 0.0, 0.0], "face_tones": [1.0, 1.0, 1.0], "gi": gi}}


@pytest.mark.parametrize("a, e", [(0.5, 0.2), (0.8, 0.1), (0.3, [0.9, 0.5, 0.2])])
def test_furnace_thick_walls(a, e):
    """Walls that fill the grid stop every cone: the cones see e·(1 + a) within 1.5% (measured:
    0.2% – 0.5% low at 6 cones)."""
    e = [e] * 3 if isinstance(e, float) else e
    out = tv.render(cavity(a, e), dtype=torch.float64)
    assert bool((out.depth > 0).all())
    expected = torch.tensor(e, dtype=torch.float64)[:, None, None] * (1 + a)
    ratio = out.radiance[0].double() / expected
    assert bool((ratio > 0.985).all() and (ratio <= 1.0 + 1e-9).all()), (ratio.min(), ratio.max())
    assert out.stats["passes"] == ["rays", "voxels.dda", "voxels.shade", *CONE_PASSES, "composite"]


@pytest.mark.parametrize("shape", ["box", "sphere", "L"])
@pytest.mark.parametrize("a, e", [(0.5, 0.2), (0.8, 0.1)])
def test_furnace_thin_walls_leak_a_bounded_share(shape, a, e):
    """Two-voxel walls with empty cells outside (test_gi's rooms): coarse levels average the walls
    with the outside, some of each cone leaks out (the known approximation of cone tracing). The
    radiance stays under e·(1 + a) and within 15% of it (measured: 2% – 12.3% low)."""
    out = tv.render(room([{"color": [a] * 3, "emission": [e] * 3}], shape=shape, gi={"method": "cone"}), dtype=torch.float64)
    ratio = out.radiance.double() / (e * (1 + a))
    assert bool((ratio > 0.85).all() and (ratio <= 1.0 + 1e-9).all()), (ratio.min(), ratio.max())


def test_open_floor_sees_the_sky():
    """Under a sky of 1, the path tracer's floor is albedo · 1 exactly; the cones' within 8% (measured
    4.4% – 6.3% low: a cone sees the floor it starts on at coarse levels), and so is their AO."""
    path = tv.render(floor({"method": "path", "bounces": 1, "samples": 4}), dtype=torch.float64)
    assert torch.allclose(path.radiance.double(), torch.full_like(path.radiance, 0.5).double(), rtol=1e-6)
    cone = tv.render(floor({"method": "cone", "ao": True}), dtype=torch.float64)
    ao = cone.aovs["ao"]
    assert bool((ao > 0.92).all() and (ao <= 1.0).all()), (ao.min(), ao.max())
    # ao = true multiplies the albedo by the cones' visibility: radiance = a · ao · indirect
    indirect = cone.radiance / (0.5 * ao)
    assert bool((indirect > 0.92).all() and (indirect <= 1.0 + 1e-9).all()), (indirect.min(), indirect.max())


def preset_scene(gi: dict, size: int) -> dict:
    scene = preset_dict("voxel-cone", width=size, height=size)
    scene["voxels"]["gi"] = gi
    scene["post"] = {}
    return scene


def rel_rmse(x: torch.Tensor, ref: torch.Tensor) -> float:
    return ((x - ref).pow(2).mean().sqrt() / ref.pow(2).mean().sqrt()).item()


def test_cone_against_path_on_the_preset():
    """voxel-cone at 20²: cones (no AO) against a 192-path bounces = 1 render (itself 1.2% from a
    1024-path one): relative RMSE of the radiance under 7% (measured 3.7%); 1 cone is worse (4.2%)
    than 6, and the distance LOD stays close (4.2%)."""
    ref = tv.render(preset_scene({"method": "path", "bounces": 1, "samples": 192}, 20)).radiance
    six = rel_rmse(tv.render(preset_scene({"method": "cone"}, 20)).radiance, ref)
    one = rel_rmse(tv.render(preset_scene({"method": "cone", "cones": 1}, 20)).radiance, ref)
    lod = rel_rmse(tv.render(preset_scene({"method": "cone", "lod": {"near": 4.0, "far": 10.0}}, 20)).radiance, ref)
    assert six < 0.07 and one > six and lod < 0.08, (six, one, lod)


def test_lod_far_away_is_bitwise_off_and_near_zero_uses_fewer_cones():
    base = cavity(0.5, [0.2] * 3, size=(6, 6))
    off = tv.render(base).radiance
    base["voxels"]["gi"] = {"method": "cone", "lod": {"near": 100.0, "far": 200.0}}
    assert torch.equal(tv.render(base).radiance, off)
    base["voxels"]["gi"] = {"method": "cone", "lod": {"near": 0.0, "far": 0.5, "cones": 1, "aperture": 60.0}}
    coarse = tv.render(base).radiance
    assert not torch.equal(coarse, off) and torch.isfinite(coarse).all()
    assert (coarse - off).abs().max() < 0.1 * off.max()


def test_mip_top_is_the_mean_of_the_base():
    g = torch.Generator().manual_seed(0)
    occ = (torch.rand(2, 5, 7, 3, generator=g, dtype=torch.float64) > 0.5).to(torch.float64)
    rad = torch.rand(2, 3, 5, 7, 3, generator=g, dtype=torch.float64)
    surf = occ * (torch.rand(2, 5, 7, 3, generator=g, dtype=torch.float64) > 0.3)
    levels = build_mips(occ, rad, surf)
    assert [lv.shape[-1] for lv in levels] == [8, 4, 2, 1]
    base = levels[0]
    assert torch.allclose(levels[-1][..., 0, 0, 0], base.mean(dim=(2, 3, 4)), rtol=1e-12)
    # the padding is empty: the top is the unpadded mean scaled by the share of the cube the grid fills
    assert torch.allclose(levels[-1][:, 4, 0, 0, 0], occ.mean(dim=(1, 2, 3)) * (5 * 7 * 3) / 8 ** 3, rtol=1e-12)
    assert torch.allclose(levels[-1][:, :3, 0, 0, 0], (rad * surf[:, None]).sum(dim=(2, 3, 4)) / 8 ** 3, rtol=1e-12)


@pytest.mark.parametrize("count", [1, 2, 6, 16])
def test_cone_directions_split_the_cosine_hemisphere(count):
    n = torch.nn.functional.normalize(torch.tensor([[0.3, -0.8, 0.2], [0.0, 0.0, -1.0]], dtype=torch.float64), dim=1)
    d = cone_directions(n, count)
    assert d.shape == (2, count, 3)
    assert torch.allclose(d.norm(dim=2), torch.ones(2, count, dtype=torch.float64))
    cos = (d * n[:, None]).sum(2)
    assert bool((cos > 0).all())
    if count > 2:  # symmetric about the normal: the mean direction is along it
        assert torch.allclose(torch.nn.functional.normalize(d.mean(1), dim=1), n, atol=1e-12)
    assert 0.0 < default_aperture(count) <= 60.0


def test_passes_only_with_cones():
    cone = tv.render(cavity(0.5, [0.2] * 3, size=(4, 4)))
    path = tv.render(cavity(0.5, [0.2] * 3, gi={"method": "path", "samples": 2}, size=(4, 4)))
    none = cavity(0.5, [0.2] * 3, size=(4, 4))
    del none["voxels"]["gi"]
    plain = tv.render(none)
    assert all(p in cone.stats["passes"] for p in CONE_PASSES) and "voxels.gi" not in cone.stats["passes"]
    assert "voxels.gi" in path.stats["passes"] and not any(p in path.stats["passes"] for p in CONE_PASSES)
    assert not any(p.startswith("voxels.gi") for p in plain.stats["passes"])
    assert not make_plan(tv.load_scene(none)).voxels.cone and "ao" not in plain.aovs


@pytest.mark.parametrize("case", ["inside", "grazing", "empty", "one_cone_lod", "shadowed_sun"])
def test_hard_cases_are_finite(case):
    gi = {"method": "cone", "ao": True}
    if case == "inside":  # the camera inside a wall: every pixel's hit is at t = 0
        scene = room([[0.6, 0.5, 0.4]], gi=gi, size=(5, 4))
        scene["camera"] = {"eye": [0.2, 0.3, 4.5], "target": [0.0, 0.0, 0.0], "fov_y": 70.0}
    elif case == "grazing":  # rays along the floor
        scene = floor(gi, size=(7, 5), eye=(0.0, 0.001, -7.5))
    elif case == "empty":
        scene = floor(gi, size=(4, 4))
        scene["voxels"]["occupancy"] = {"function": {"fn": lambda c: torch.zeros(c.shape[0], dtype=torch.long)}}
    elif case == "one_cone_lod":
        scene = floor({"method": "cone", "cones": 1, "aperture": 89.0, "steps": 1,
                       "lod": {"near": 0.0, "far": 1e-3, "cones": 1, "aperture": 1e-3}}, size=(5, 5))
    else:
        scene = preset_scene({"method": "cone", "ao": True, "max_distance": 2.0}, 9)
    out = tv.render(scene)
    assert torch.isfinite(out.radiance).all() and torch.isfinite(out.image).all()
    if case == "empty":
        assert not any(p.startswith("voxels.gi") for p in out.stats["passes"])


def test_per_scene_apertures_in_one_batch():
    a, b = cavity(0.5, [0.2] * 3, size=(5, 4)), cavity(0.8, [0.1] * 3, size=(5, 4))
    b["voxels"]["gi"] = {"method": "cone", "aperture": 20.0}
    a["voxels"]["gi"] = {"method": "cone", "aperture": 45.0}
    both = tv.render([a, b])
    assert torch.equal(both.radiance[0], tv.render(a).radiance[0])
    assert torch.equal(both.radiance[1], tv.render(b).radiance[0])


def test_path_lod_far_away_is_bitwise_off_and_cheaper_near_zero():
    """`voxels.gi.lod` on the path tracer: with every hit nearer than `near` the render is the same to
    the bit; with every hit beyond `far` each pixel traces lod.samples paths (its first ones), so
    the furnace still holds to 1%."""
    gi = {"method": "path", "bounces": 2, "samples": 6}
    scene = room([{"color": [0.5] * 3, "emission": [0.2] * 3}], gi=gi, size=(6, 5))
    off = tv.render(scene, dtype=torch.float64)
    scene["voxels"]["gi"] = {**gi, "lod": {"near": 100.0, "far": 200.0, "samples": 1}}
    assert torch.equal(tv.render(scene, dtype=torch.float64).radiance, off.radiance)
    scene["voxels"]["gi"] = {**gi, "lod": {"near": 0.0, "far": 0.1, "samples": 2}}
    few = tv.render(scene, dtype=torch.float64)
    assert torch.allclose(few.radiance.double(), torch.full_like(few.radiance, 0.2 * 1.75).double(), rtol=0.01)
    assert few.stats["voxel_steps"] < off.stats["voxel_steps"]
