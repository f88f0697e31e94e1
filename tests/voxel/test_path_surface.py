"""Voxels under `[path]` (torchvol/voxel/path_surface.py): Lambert faces of the materials' colour
and emission that stop flights and shadow rays.

Analytic oracles: the furnace room (a closed room of albedo a emitting e shows e·Σ_{k=0..B} a^k,
as voxel GI's does); a flat voxel floor under a sun and a constant sky S is a·(E·cos θ + S) for
any bounce count, as the marched faces with ambient S; one bounce under a cloud is the march's
single scattering."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import assert_close
from test_gi import room

import torchvol as tv
from torchvol.renderer.executor import camera_for
from torchvol.schema.validate import SceneError
from torchvol.voxel.ggx import reflectance_lanes

F64 = torch.float64


def _mean_and_error(values: torch.Tensor) -> tuple[float, float]:
    values = values.double().reshape(-1)
    return float(values.mean()), float(values.std() / math.sqrt(values.numel()))


@pytest.mark.parametrize("shape", ["box", "L"])
@pytest.mark.parametrize("a, e, bounces", [(0.5, 0.2, 2), (0.8, 0.1, 6)])
def test_the_furnace_room(shape, a, e, bounces, one_thread):
    """Every path meets walls only; past `ROULETTE_AFTER` scatterings roulette makes paths differ,
    unbiased: the image's mean within five standard errors (exact before)."""
    scene = room([{"color": [a] * 3, "emission": [e] * 3}], shape=shape)
    scene["path"] = {"bounces": bounces, "samples": 8}
    out = tv.render(scene)
    expected = e * sum(a**k for k in range(bounces + 1))
    mean, error = _mean_and_error(out.radiance)
    assert bool((out.depth > 0).all()), "the camera must see walls only"
    assert abs(mean - expected) <= 5.0 * error + 1e-6, f"furnace room: {mean:.6g} ± {error:.2g} against {expected:.6g}"
    assert out.stats["plan"]["path"]["backend"] == "drjit"
    eager = tv.render(scene, compile="off")
    gap = float((eager.radiance - out.radiance).abs().max())
    assert gap < 1e-5, f"kernel and eager paths differ by {gap:.3g}"


def _floor(*, albedo: float = 0.4, sky: float = 0.25, medium: dict | None = None) -> dict:
    """A voxel floor (top face at y = 0) of one colour under a slanted sun and a constant sky, the
    camera looking down at it at 45°; `medium` a box over it."""
    scene = {"image": {"width": 6, "height": 6}, "camera": {"eye": [0.3, 3, -3], "target": [0.3, 0, 0], "fov_y": 30},
             "sky": {"kind": "constant", "radiance": [sky] * 3},
             "lights": [{"direction": [0.3, 1.0, 0.2], "intensity": 2.0, "shadow": {"steps": 64}}],
             "voxels": {"occupancy": {"sdf": {"shape": {"box": {"center": [0.0, -1.0, 0.0], "half_size": [12.0, 1.0, 12.0]}},
                                              "material": 1}},
                        "cells": {"min": [-12, -2, -12], "max": [12, 1, 12]}, "materials": [[albedo] * 3],
                        "ambient": [sky] * 3, "face_tones": [1.0, 1.0, 1.0], "shadow": {}},
             "march": {"quality": "high", "steps": 192, "closed_form": False}}
    if medium is not None:
        scene["volumes"] = [{"bounds": {"box": {"min": [-2, 0.3, -2], "max": [2, 1.3, 2]}}, **medium}]
    return scene


def test_a_voxel_floor_under_a_sun_and_a_sky_is_lambert_shaded(one_thread):
    """Every path meets the floor, takes the sun's a·E·cos θ and bounces into the sky S, whatever
    its direction: a·(E·cos θ + S), for 1 and 4 bounces, as the marched faces (ambient S) give it."""
    a, sky = 0.4, 0.25
    scene = _floor(albedo=a, sky=sky)
    expected = a * (2.0 / math.sqrt(0.3**2 + 1.0 + 0.2**2) + sky)
    for bounces in (1, 4):
        out = tv.render({**scene, "path": {"bounces": bounces, "samples": 2}})
        assert_close(out.radiance, expected, atol=1e-5, what=f"path-traced voxel floor, {bounces} bounces")
    assert_close(tv.render(scene).radiance, expected, atol=1e-5, what="marched voxel floor")


def test_one_bounce_over_voxels_is_the_marched_single_scattering(one_thread):
    """A cloud over the floor, lit by a sun, no sky: one bounce takes the cloud's single scattering
    and the floor's direct light through the cloud's shadow, as the march does; on the march
    (`single = "march"`) one bounce is the march itself."""
    scene = _floor(sky=0.0, medium={"density": {"constant": 1.0}, "sigma_t": 1.2, "albedo": 0.8, "phase": {"hg": {"g": 0.5}}})
    march = tv.render(scene, dtype=F64)
    seeds = 4
    traced = tv.render([{**scene, "path": {"bounces": 1, "samples": 48}}] * seeds, seed=list(range(seeds)))
    mean, error = _mean_and_error(traced.radiance.double().mean(dim=(1, 2, 3)))
    expected = float(march.radiance.double().mean())
    assert abs(mean - expected) <= 5.0 * error and error < 0.05 * expected, (
        f"single scattering over voxels: path {mean:.6g} ± {error:.2g}, march {expected:.6g}")
    one = tv.render({**scene, "path": {"bounces": 1, "samples": 2, "single": "march"}})
    assert torch.equal(one.radiance, tv.render(scene).radiance)


def test_shadows_stop_at_the_voxels(one_thread):
    """A roof over part of the floor (x < 2, 5 above it), no sky, one bounce: where the roof stands
    between the floor and the sun (x < 0.5 under this sun) the floor is black, elsewhere a·E·cos θ;
    the marched faces agree pixel by pixel."""
    scene = _floor(sky=0.0)
    scene["voxels"]["occupancy"] = {"sdf": {"shape": {"union": [
        {"box": {"center": [0.0, -1.0, 0.0], "half_size": [12.0, 1.0, 12.0]}},
        {"box": {"center": [-5.0, 6.0, 0.0], "half_size": [7.0, 1.0, 12.0]}}]}, "material": 1}}
    scene["voxels"]["cells"] = {"min": [-12, -2, -12], "max": [12, 8, 12]}
    scene["camera"] = {"eye": [0.3, 2, -3], "target": [0.3, 0, 0], "fov_y": 30}
    out = tv.render({**scene, "path": {"bounces": 1, "samples": 2}})
    lit = 0.4 * 2.0 / math.sqrt(0.3**2 + 1.0 + 0.2**2)
    values = out.radiance[0, 0]
    assert float(values.min()) == 0.0 and abs(float(values.max()) - lit) < 1e-5, "shadowed and lit floor both in view"
    assert_close(out.radiance, tv.render(scene).radiance, atol=1e-5, what="path-traced against marched shadows")


def _rounded_floor() -> dict:
    """A floor of rounded voxels (radius 0.05–0.4 by cell) under the sun straight overhead, no sky."""
    return {"image": {"width": 24, "height": 18}, "camera": {"eye": [0.2, 4.0, -5.0], "target": [0.2, 0.0, 0.0], "fov_y": 40},
            "sky": {"kind": "constant", "radiance": [0.0, 0.0, 0.0]},
            "lights": [{"direction": [0.0, 1.0, 0.0], "intensity": 2.0}],
            "voxels": {"occupancy": {"sdf": {"shape": {"box": {"center": [0.0, -0.5, 0.0], "half_size": [6.0, 0.5, 6.0]}},
                                             "material": 1}},
                       "cells": {"min": [-6, -2, -6], "max": [6, 1, 6]}, "materials": [[0.6, 0.5, 0.4]],
                       "ambient": [0.0] * 3, "face_tones": [1.0, 1.0, 1.0], "shadow": {},
                       "rounded": {"radius_min": 0.05, "radius_range": 0.35, "steps": 12, "threshold": 0.002}}}


def test_rounded_voxels_are_traced_as_the_march_finds_them(one_thread):
    """Rounded voxels under a sun straight overhead, one bounce: every pixel is the marched
    image (the same rounded box and normal, `shade.rounded_lanes` on both sides; a shadow ray that
    leaves its own box's cell sees nothing overhead), in the kernel and eagerly; and the march
    lights every point whose normal faces the sun (its shadow rays once started inside their own
    occupied cell and left the boxes' rounded rims dark)."""
    scene = _rounded_floor()
    march = tv.render(scene, aovs=("normal",))
    traced = {c: tv.render({**scene, "path": {"bounces": 1, "samples": 1}}, compile=c).radiance for c in ("kernels", "off")}
    assert_close(traced["kernels"], march.radiance, atol=1e-5, what="path-traced rounded voxels against the march")
    assert_close(traced["off"], traced["kernels"], atol=1e-5, what="rounded voxels eagerly against the kernel")
    facing = (march.aovs["normal"][:, 1] > 1e-3) & (march.depth[:, 0] > 0)
    lit = march.radiance.amax(1) > 0
    assert int(facing.sum()) > 100 and torch.equal(lit, facing), f"{int((lit != facing).sum())} pixels lit otherwise than n·l"
    # radius 0 is the cube, path-traced too (a slanted sun: shadows and bounces off the faces)
    scene["lights"][0]["direction"], scene["sky"]["radiance"] = [0.3, 0.8, -0.4], [0.2, 0.3, 0.4]
    cube = {**scene, "voxels": {**scene["voxels"], "rounded": None}, "path": {"bounces": 3, "samples": 2}}
    zero = {**cube, "voxels": {**scene["voxels"], "rounded": {"radius_min": 0.0, "radius_range": 0.0, "threshold": 0.002}}}
    assert_close(tv.render(zero).radiance, tv.render(cube).radiance, atol=1e-5, what="radius-0 rounded voxels against cubes")


@pytest.mark.parametrize("key, value", [("glow", {}), ("fog", {"density": 0.1}), ("water", {"level": 0.0})])
def test_what_a_path_cannot_trace_is_refused(key, value):
    scene = {**_floor(), "path": {"bounces": 2, "samples": 1}}
    scene["voxels"] = {**scene["voxels"], key: value}
    with pytest.raises(SceneError, match=f"voxels.{key}"):
        tv.render(scene)


def test_textured_faces_take_their_texels_as_the_march_does(one_thread):
    """Two scenes of other atlases (sizes, tiles) and materials, one Lambert and one GGX, in one
    batch: one bounce under a sun, no sky, is each one's marched image (the texel times the
    material's colour, `shade.texel_lanes` on both sides) and each renders as alone."""
    rng = np.random.default_rng(0)
    scenes = []
    for size, tiles, material in ((16, 4, [0.9, 0.8, 0.7]), (24, 2, {"color": [0.7, 0.7, 0.9], "roughness": 0.4})):
        scene = _floor(sky=0.0)
        del scene["sky"]
        atlas = (rng.random((size, size, 3)) * 255).astype(np.uint8)
        scene["voxels"] = {**scene["voxels"], "texture": {"atlas": atlas, "tiles": tiles}, "materials": [material],
                           "ambient": [0.0] * 3}
        scene["image"] = {"width": 24, "height": 16}
        scenes.append(scene)
    traced = tv.render([{**sc, "path": {"bounces": 1, "samples": 1}} for sc in scenes], seed=[1, 2])
    for b, scene in enumerate(scenes):
        march = tv.render(scene, seed=b + 1)  # (the same jittered sub-samples)
        assert float(march.radiance.std()) > 0.05  # the texture shows
        gap = ((traced.radiance[b] - march.radiance[0]).abs() / march.radiance[0].abs().clamp_min(1e-3)).max()
        assert float(gap) < 1e-4, f"scene {b}: path-traced and marched textures differ by {float(gap):.2e} relative"
        alone = tv.render({**scene, "path": {"bounces": 1, "samples": 1}}, seed=b + 1)
        assert torch.equal(traced.radiance[b], alone.radiance[0])


@pytest.mark.parametrize("roughness, metallic", [(0.3, 0.0), (0.6, 1.0), (0.05, 0.5)])
def test_a_ggx_floor_takes_the_marched_direct_light(roughness, metallic, one_thread):
    """A GGX floor (the marched faces' `ggx_reflect`, the paths' `reflectance_lanes`: one source)
    under a sun, no sky, one bounce: every path's next event is the marched direct light, pixel by
    pixel (its mirror reflections, a stand-in, dropped)."""
    scene = _floor(sky=0.0)
    del scene["sky"]
    scene["voxels"] = {**scene["voxels"], "materials": [{"color": [0.8, 0.5, 0.2], "roughness": roughness, "metallic": metallic}],
                       "ambient": [0.0] * 3, "reflections": {"bounces": 1}}
    scene["lights"][0]["direction"] = [0.1, 1.0, 0.6]  # the highlight in view
    out = tv.render({**scene, "path": {"bounces": 1, "samples": 1}})
    march = tv.render({**scene, "voxels": {**scene["voxels"], "reflections": None}})
    assert float(march.radiance.std()) > 0.0
    # relative: a sharp highlight (roughness 0.05: D peaks at ~1e5) turns float32's ulps in the hit
    # point and view into ~1e-3 of the value
    gap = ((out.radiance - march.radiance).abs() / march.radiance.abs().clamp_min(1e-3)).max()
    assert float(gap) < 3e-3, f"GGX floor: path-traced and marched differ by {float(gap):.2e} relative"


@pytest.mark.parametrize("roughness, metallic, grazing", [(0.3, 0.0, False), (0.5, 1.0, False), (0.3, 1.0, True)])
def test_a_ggx_floor_under_a_sky_reflects_its_directional_albedo(roughness, metallic, grazing, one_thread):
    """A GGX floor under a constant sky S, one bounce: each pixel sees S·∫ BRDF cos dω over the
    hemisphere (a dense quadrature of `reflectance_lanes` / π towards that pixel's view): the
    bounce's GGX (its visible normals) and cosine lobes drawn, weighted by their mixture's density,
    unbiased, at 45° and at a grazing view (2.3–6.3° over the floor, where drawing from the normals'
    density D(h)·(n·h) gave 6× the noise). The image's mean over four seeds within five standard
    errors; at the grazing view a pixel's relative noise under 4% (1.65%; drawn from the normals' density: 9.8%)."""
    sky = 0.7
    scene = _floor(sky=sky)
    if grazing:
        scene["camera"] = {"eye": [0.3, 0.6, -6.0], "target": [0.3, 0.0, 2.0], "fov_y": 4.0}
    scene["voxels"] = {**scene["voxels"], "materials": [{"color": [0.8, 0.5, 0.2], "roughness": roughness, "metallic": metallic}],
                       "ambient": [0.0] * 3}
    scene["lights"][0]["intensity"] = 0.0
    seeds = 4
    out = tv.render([{**scene, "path": {"bounces": 1, "samples": 64}}] * seeds, seed=list(range(seeds)), keep_context=True)
    rays = camera_for(out.context.batch).ray_range(0, 36, spp=1)
    view = -rays.directions.double()  # towards the eye, per pixel
    theta = (torch.arange(400, dtype=F64) + 0.5) / 400 * (math.pi / 2)
    phi = (torch.arange(400, dtype=F64) + 0.5) / 400 * (2 * math.pi)
    t, p = torch.meshgrid(theta, phi, indexing="ij")
    light = torch.stack([torch.sin(t) * torch.cos(p), torch.cos(t), torch.sin(t) * torch.sin(p)], -1).reshape(-1, 3)
    solid = (torch.sin(t) * (math.pi / 2 / 400) * (2 * math.pi / 400)).reshape(-1)
    cols = lambda x: list(x.unbind(-1))  # noqa: E731
    up = [torch.zeros_like(light[:, 0]), torch.ones_like(light[:, 0]), torch.zeros_like(light[:, 0])]
    expected = []
    for v in view:
        vv = [c.expand_as(light[:, 0]) for c in v]
        albedo = [torch.full_like(light[:, 0], c) for c in (0.8, 0.5, 0.2)]
        refl = reflectance_lanes(up, vv, cols(light), albedo, torch.full_like(light[:, 0], roughness),
                                 torch.full_like(light[:, 0], metallic))
        expected.append(torch.stack([(r * solid).sum() / math.pi * sky for r in refl]))
    expected = torch.stack(expected).mean(0)
    means = out.radiance.double().mean(dim=(2, 3))  # (seeds, 3)
    for c in range(3):
        mean, error = _mean_and_error(means[:, c])
        assert abs(mean - float(expected[c])) <= 5.0 * error + 1e-4 * float(expected[c]), (
            f"colour {c}: path {mean:.5g} ± {error:.2g}, quadrature {float(expected[c]):.5g}")
    noise = float(out.radiance.double().std(dim=0).pow(2).mean().sqrt() / out.radiance.double().mean())
    print(f"a pixel's relative noise {noise:.2%}")
    assert not grazing or noise < 0.04, f"grazing view: a pixel's relative noise {noise:.2%}"


@pytest.mark.parametrize("name", ["voxel-gi", "voxel-carved-box", "voxel-cone", "voxel-pbr", "voxel-rounded"])
def test_voxel_presets_path_trace(name, one_thread):
    """The voxel presets whose looks a path has (their stand-ins dropped) render under `[path]`:
    finite, non-negative, the plan saying so, no shadow pass of the march."""
    scene = tv.preset(name, width=6, height=6).model_dump()
    scene["path"] = {"bounces": 4, "samples": 1}
    out = tv.render(scene)
    assert torch.isfinite(out.radiance).all() and float(out.radiance.min()) >= 0.0 and float(out.radiance.sum()) > 0
    assert "path" in out.stats["passes"] and not [p for p in out.stats["passes"] if "shadow" in p or "gi" in p]


def test_a_batch_renders_each_voxel_scene_as_alone(one_thread):
    """Scenes of other grids, materials and cell ranges in one batch: each renders as alone (the
    walk's per-lane range, base and placement; its material rows)."""
    a = {**room([{"color": [0.5, 0.4, 0.3], "emission": [0.2] * 3}], shape="L", size=(7, 5)), "path": {"bounces": 3, "samples": 2}}
    b = {**_floor(albedo=0.7), "image": {"width": 7, "height": 5}, "path": {"bounces": 3, "samples": 2}}
    b["voxels"] = {**b["voxels"], "origin": [0.5, 0.0, -0.25], "voxel_size": 0.5}
    a.update(lights=b["lights"], march=b["march"], sky={"kind": "constant", "radiance": [0.3, 0.2, 0.1]})
    batch = tv.render([a, b], seed=[1, 2])
    for i, (scene, seed) in enumerate(((a, 1), (b, 2))):
        alone = tv.render(scene, seed=seed)
        assert torch.equal(batch.radiance[i], alone.radiance[0]), f"scene {i} differs alone"


def test_voxels_on_a_terrain_are_shaded_as_the_march_shades_them(one_thread):
    """Voxels standing on a flat terrain (`path.surfaces`: each ray the nearer, as the march's
    surface pass), a sun, no sky, one bounce: every path takes its surface's a·E·cos θ through the
    other surface's shadow, exactly as the marched surfaces do, pixel by pixel."""
    scene = _floor(sky=0.0)
    del scene["sky"]
    scene["voxels"]["occupancy"] = {"sdf": {"shape": {"box": {"center": [-0.5, 1.0, 0.5], "half_size": [1.0, 1.0, 1.0]}},
                                            "material": 1}}
    scene["voxels"]["cells"] = {"min": [-3, 0, -2], "max": [2, 3, 3]}
    scene["terrain"] = {"amplitude": 0.0, "color": [0.6, 0.5, 0.3], "rock_color": [0.6, 0.5, 0.3], "ambient": [0.0, 0.0, 0.0],
                        "steps": 64}
    scene["camera"] = {"eye": [2.5, 3, -3.5], "target": [-0.3, 0.5, 0.3], "fov_y": 45}
    scene["image"] = {"width": 12, "height": 10}
    out = tv.render({**scene, "path": {"bounces": 1, "samples": 1}})
    march = tv.render(scene)
    assert {float(v) for v in out.radiance[0, 0].unique()} > {0.0}, "both surfaces and a shadow in view"
    assert_close(out.radiance, march.radiance, atol=1e-4, what="voxels on a terrain, path-traced against marched")
