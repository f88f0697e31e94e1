"""`[voxels]` and `[terrain]` in one scene (renderer/surfaces.py): each primary ray takes the nearer
hit (depth against the analytic plane and box), the voxels shadow the terrain and the terrain the
voxels, the volumes' shadow rays see the voxels, the labels name the surface met first, a batch
renders each scene as alone, nothing is NaN, and the plan records the passes that run."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import assert_close

import torchvol as tv
from torchvol.renderer.plan import make_plan

GROUND, AMBIENT, SUN_INTENSITY = (0.3, 0.5, 0.2), (0.1, 0.1, 0.1), 2.0
BOX_MIN, BOX_MAX = (-1.0, 0.0, -1.0), (1.0, 2.0, 1.0)  # the voxel block standing on the plane y = 0


def block(cells: torch.Tensor) -> torch.Tensor:
    """A 2×2×2 block of cells: material 1 in the bottom layer, 2 in the top one."""
    return torch.where(cells[:, 1] == 0, 1, 2)


def scene(*, sun=(1.0, 1.0, 0.0), eye=(-2.0, 5.0, -7.0), terrain=True, voxels=True, intensity=SUN_INTENSITY, **extra) -> dict:
    """A flat terrain (the plane y = 0) with a voxel block standing on it, lit by a shadowed sun."""
    out = {"image": {"width": 32, "height": 24},
           "camera": {"eye": list(eye), "target": [0.0, 0.5, 0.0], "fov_y": 55.0},
           "sky": {"kind": "constant", "radiance": [0.3, 0.4, 0.6]},
           "lights": [{"kind": "sun", "direction": list(sun), "intensity": intensity, "shadow": {"steps": 4}}],
           "march": {"quality": "draft"}}
    if terrain:
        out["terrain"] = {"base": 0.0, "amplitude": 0.0, "color": list(GROUND), "ambient": list(AMBIENT)}
    if voxels:
        out["voxels"] = {"occupancy": {"function": {"fn": block}}, "cells": {"min": [-1, 0, -1], "max": [1, 2, 1]},
                         "materials": [[0.8, 0.3, 0.2], [0.2, 0.3, 0.8]], "shadow": {"steps": 16}}
    return {**out, **extra}


def pixel_rays(out) -> tuple[torch.Tensor, torch.Tensor]:
    """(eye [3], rays [H, W, 3]) in float64: world point = eye + depth · ray at each pixel centre."""
    K, w2c = out.camera.K[0].double(), out.camera.world_to_camera[0].double()
    h, w = out.depth.shape[-2:]
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    cam = torch.stack([u, v, torch.ones_like(u)], dim=-1) @ torch.linalg.inv(K).T
    rot = w2c[:3, :3]
    return -rot.T @ w2c[:3, 3], cam @ rot


def world_points(out) -> torch.Tensor:
    """[H, W, 3] world points of the depth map."""
    eye, rays = pixel_rays(out)
    return eye + out.depth[0, 0].double()[..., None] * rays


def analytic_depth(out) -> torch.Tensor:
    """[H, W] planar depth of the nearer of the plane y = 0 and the block (0: neither)."""
    eye, rays = pixel_rays(out)
    plane = torch.where(rays[..., 1] < 0, -eye[1] / rays[..., 1], torch.full_like(rays[..., 1], math.inf))
    lo, hi = torch.tensor(BOX_MIN, dtype=torch.float64), torch.tensor(BOX_MAX, dtype=torch.float64)
    a, b = (lo - eye) / rays, (hi - eye) / rays
    near, far = torch.minimum(a, b).amax(dim=-1), torch.maximum(a, b).amin(dim=-1)
    box = torch.where((near <= far) & (near > 0), near, torch.full_like(near, math.inf))
    nearest = torch.minimum(plane, box)
    return torch.where(torch.isfinite(nearest), nearest, torch.zeros_like(nearest))


def test_each_ray_takes_the_nearer_surface(one_thread):
    out = tv.render(scene(), aovs=["instance"])
    expected = analytic_depth(out)
    assert bool((expected > 0).all()), "the view is all plane and block"
    assert_close(out.depth[0, 0].double(), expected, atol=2e-4 * float(expected.max()), what="depth vs the plane and box")
    ground = out.aovs["material"][0, 0] == 3  # the terrain's id: one past the voxels' two materials
    block_px = (out.aovs["material"][0, 0] == 1) | (out.aovs["material"][0, 0] == 2)
    assert bool((ground | block_px).all()) and ground.sum() > 50 and block_px.sum() > 30
    # the block stands in front of the plane where its box is nearer: exactly the pixels the voxels won
    on_plane = world_points(out)[..., 1].abs() < 1e-3
    assert torch.equal(ground, on_plane)
    assert torch.equal(out.aovs["instance"][0, 0], out.aovs["material"][0, 0]), "no volumes: instance = surface id"
    assert_close(out.aovs["normal"][0, :, ground].T, torch.tensor([[0.0, 1.0, 0.0]]).expand(int(ground.sum()), 3))
    # against each surface rendered alone: the nearer of the two depths per pixel
    alone = [tv.render(scene(terrain=False)).depth, tv.render(scene(voxels=False)).depth]
    nearer = torch.where(alone[0] == 0, alone[1], torch.minimum(alone[0], alone[1]))
    assert torch.equal(out.depth, nearer)


def test_the_block_shadows_the_ground(one_thread):
    """A 45° sun from +x: the block's shadow on the ground reaches 2 units towards −x."""
    out = tv.render(scene(sun=(1.0, 1.0, 0.0)), aovs=["sun_visibility"])
    p = world_points(out)
    ground = out.aovs["material"][0, 0] == 3
    x, z = p[..., 0], p[..., 2]
    shade = ground & (x > -2.8) & (x < -1.2) & (z.abs() < 0.8)
    lit = ground & ((z.abs() > 1.3) | (x > 1.2) | (x < -3.2))
    assert shade.sum() >= 4 and lit.sum() >= 20
    color = torch.tensor(GROUND)
    radiance = out.radiance[0].permute(1, 2, 0)
    assert_close(radiance[shade], (color * torch.tensor(AMBIENT)).expand(int(shade.sum()), 3), atol=1e-5,
                 what="ground in the block's shadow: ambient only")
    sunlit = color * (torch.tensor(AMBIENT) + SUN_INTENSITY * math.cos(math.pi / 4))
    assert_close(radiance[lit], sunlit.expand(int(lit.sum()), 3), atol=1e-4, what="sunlit ground")
    vis = out.aovs["sun_visibility"][0, 0]
    assert bool((vis[shade] == 0).all()) and bool((vis[lit] == 1).all())
    assert "terrain.shadow0.voxels" in out.stats["passes"]


def test_the_ground_shadows_the_block(one_thread):
    """A sun just under the horizon from +x: the block's +x face turns to it (n·l > 0), but every
    shadow ray from the face meets the ground within 10 units: the face is as dark as unlit."""
    sun, eye = (1.0, -0.25, 0.0), (5.0, 4.0, -6.0)
    out = tv.render(scene(sun=sun, eye=eye), aovs=["sun_visibility"])
    face = (out.aovs["normal"][0, 0] == 1.0) & (out.aovs["material"][0, 0] < 3)  # the block's +x face
    assert face.sum() >= 6
    alone = tv.render(scene(sun=sun, eye=eye, terrain=False))  # the face lit: nothing blocks the sun
    dark = tv.render(scene(sun=sun, eye=eye, terrain=False, intensity=0.0))
    radiance, lit, unlit = (r.radiance[0].permute(1, 2, 0)[face] for r in (out, alone, dark))
    assert bool((lit > unlit + 0.05).all())
    assert_close(radiance, unlit, atol=1e-6, what="the +x face in the ground's shadow")
    assert bool((out.aovs["sun_visibility"][0, 0][face] == 0).all())
    assert bool((out.aovs["shadow"][0, 0][face] == 0).all())
    assert "voxels.shadow0.terrain" in out.stats["passes"]


def volume_scene(**extra) -> dict:
    """The block and the ground, and a dense slab of medium beside the block on its −x side, lit by
    a 45° sun from +x: the block's shadow falls across the slab's top where |z| < 1."""
    medium = {"bounds": {"box": {"min": [-3.0, 0.3, -3.0], "max": [-1.3, 0.8, 3.0]}}, "density": {"constant": 1.0},
              "sigma_t": 40.0, "albedo": 1.0}
    return scene(sun=(1.0, 1.0, 0.0), eye=(-6.0, 6.0, -4.0), volumes=[medium], **extra)


def test_the_block_shadows_a_medium(one_thread):
    out = tv.render(volume_scene())
    p, inside = world_points(out), out.alpha[0, 0] > 0.99
    top = inside & ((p[..., 1] - 0.8).abs() < 0.1) & (p[..., 0] > -2.1) & (p[..., 0] < -1.4)
    shade, lit = top & (p[..., 2].abs() < 0.7), top & (p[..., 2].abs() > 1.3)
    assert shade.sum() >= 2 and lit.sum() >= 4
    luminance = out.radiance[0].sum(dim=0)
    assert float(luminance[shade].max()) < 0.25 * float(luminance[lit].min())
    assert "volume0.shadow0.voxels" in out.stats["passes"]


def test_the_plan_records_the_passes_that_ran(one_thread):
    s = tv.load_scene(volume_scene(lights=[
        {"kind": "sun", "direction": [1.0, 1.0, 0.0], "intensity": 2.0, "shadow": {"steps": 4}},
        {"kind": "point", "position": [2.0, 3.0, -2.0], "intensity": 4.0, "shadow": {"steps": 4}}]))
    out = tv.render(s, aovs=["sun_visibility", "instance"])
    planned, passes = make_plan(s, ("sun_visibility", "instance")).names(), out.stats["passes"]
    assert planned == out.stats["plan"]["passes"]
    # the passes ran in the planned order; an occluder's pass that no shadow ray crossed did not run
    assert [n for n in planned if n in passes] == passes
    assert all(n.startswith("voxels.shadow") and n.endswith(".volume0") for n in set(planned) - set(passes))
    for l in (0, 1):
        assert {f"terrain.shadow{l}.voxels", f"voxels.shadow{l}.terrain", f"volume0.shadow{l}.voxels"} <= set(passes)
    assert passes.index("terrain.trace") < passes.index("voxels.dda") < passes.index("volume0.march")
    # one surface: only its own (a scene pays only for what it has); the volumes' shadow rays see it
    media = volume_scene()["volumes"]
    voxels_only = make_plan(tv.load_scene(scene(terrain=False, volumes=media))).names()
    terrain_only = make_plan(tv.load_scene(scene(voxels=False, volumes=media))).names()
    assert not any(n.endswith(".terrain") for n in voxels_only) and "volume0.shadow0.voxels" in voxels_only, voxels_only
    assert not any(n.endswith(".voxels") for n in terrain_only), terrain_only


def test_finite_with_hills_point_lights_media_and_labels(one_thread):
    hills = {"seed": 5, "base": 0.3, "amplitude": 1.2, "frequency": 0.4, "octaves": 3, "steps": 64}
    s = volume_scene(terrain=True, lights=[
        {"kind": "sun", "direction": [0.3, 0.4, -0.5], "intensity": 2.0, "shadow": {"steps": 3}},
        {"kind": "point", "position": [0.5, 2.5, -1.5], "intensity": 3.0, "shadow": {"steps": 3}}])
    s["terrain"] = {**s["terrain"], **hills}
    for camera in ({"eye": [0.0, 0.4, -6.0], "target": [0.0, 0.5, 0.0]}, {"eye": [-2.0, -3.0, -4.0], "target": [0.0, 0.0, 0.0]}):
        out = tv.render({**s, "camera": camera}, aovs=["sun_visibility", "instance", "optical_thickness"])
        for name, value in {"image": out.image, "radiance": out.radiance, "depth": out.depth, "alpha": out.alpha,
                            **out.aovs}.items():
            assert bool(torch.isfinite(value).all()), name
        assert bool((out.depth >= 0).all())


def test_the_terrains_shadow_rays_walk_the_voxels_inside_its_shading_kernel(monkeypatch, one_thread):
    """The terrain's shading as one kernel whose shadow and sky rays walk the voxels
    (`kernel_march.occluder_lanes`) before crossing the medium: its passes each their own kernel
    (`surface_shadows`) within 1e-6 of its radiance (bitwise on an AVX2 CPU; on an AVX-512 one,
    2026-12-08, three of 768 pixels lit by the point light 2.4e-7 apart, the cause not found),
    within the tolerance table of eager, the block's shadow on the ground and the medium kept."""
    from torchvol.runtime.compilation import drjit_available
    from torchvol.volume import kernel_march

    if not drjit_available():
        pytest.skip("Dr.Jit's LLVM backend is not available")
    s = volume_scene(terrain=True, lights=[
        {"kind": "sun", "direction": [1.0, 1.0, 0.3], "intensity": 2.0, "shadow": {"steps": 3}},
        {"kind": "point", "position": [0.5, 2.5, -1.5], "intensity": 3.0, "shadow": {"steps": 3}}])
    s["terrain"] = {**s["terrain"], "ambient_visibility": "march"}
    eager = tv.render(s, compile="off")
    calls = []
    shadows = kernel_march.surface_shadows
    monkeypatch.setattr(kernel_march, "surface_shadows", lambda ctx, use, *a: calls.append(use.name) or shadows(ctx, use, *a))
    fused = tv.render(s)
    assert not [n for n in calls if n.startswith("terrain.")], calls  # none of the terrain's rays traced apart
    monkeypatch.setattr(kernel_march, "surface_lanes_of", lambda ctx, uses, s: None)
    parts = tv.render(s)
    assert {"terrain.shadow0", "terrain.shadow1", "terrain.ambient"} <= set(calls)
    assert_close(fused.radiance, parts.radiance, atol=1e-6 * float(parts.radiance.abs().max()), what="fused against its passes apart")
    assert fused.stats["density_evals"] == parts.stats["density_evals"] == eager.stats["density_evals"]
    assert_close(fused.radiance, eager.radiance, atol=5e-4 * float(eager.radiance.abs().max()), what="fused against eager")
    assert {"terrain.shadow0.voxels", "terrain.shadow1.voxels", "terrain.ambient.voxels"} <= set(fused.stats["passes"])


def test_a_batch_renders_each_scene_as_alone(one_thread):
    a = tv.load_scene(volume_scene())
    b = tv.load_scene(a, {"lights[0].direction": [0.6, 1.0, 0.3], "terrain.color": [0.5, 0.4, 0.3],
                          "voxels.materials[0]": [0.1, 0.9, 0.4], "camera.eye": [-5.0, 4.0, -5.0]})
    both = tv.render([a, b], seed=[1, 2], aovs=["instance", "sun_visibility"])
    for i, (sc, seed) in enumerate(((a, 1), (b, 2))):
        alone = tv.render(sc, seed=seed, aovs=["instance", "sun_visibility"])
        for key in ("image", "radiance", "depth", "alpha"):
            assert torch.equal(getattr(both, key)[i], getattr(alone, key)[0]), (i, key)
        for key, value in alone.aovs.items():
            assert torch.equal(both.aovs[key][i], value[0]), (i, key)
    assert not torch.equal(both.radiance[0], both.radiance[1])
    for i in (0, 1):  # each scene shows the block (materials 1, 2) and the ground (3)
        assert {1.0, 2.0, 3.0} <= set(both.aovs["material"][i].unique().tolist())
