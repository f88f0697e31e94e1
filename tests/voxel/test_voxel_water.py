"""`voxels.water`: Fresnel, refraction and TIR against closed forms; a flat water plane mirrors a
voxel; a camera under water sees the sky only inside Snell's window, attenuated by Beer-Lambert;
rays along the plane stay finite; the seed's water code on llvmpipe; no water key, no water pass."""

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import assert_close
from hypothesis import given, settings
from hypothesis import strategies as st

import torchvol as tv
from torchvol.measure.glsl import gl_context, run_fragment, shadertoy_source
from torchvol.renderer.plan import make_plan
from torchvol.voxel.water import beer, fresnel, plane_hit, reflect, refract, wave_normal

pytestmark = pytest.mark.usefixtures("one_thread")

IOR = 1.33


def pixel_rays(out):
    """World eye [3] and unit ray directions (H, W, 3) through the pixel centres of `out`'s camera."""
    cam = out.camera
    h, w = cam.height, cam.width
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    pix = torch.stack([u, v, torch.ones_like(u)], dim=-1)
    d_cam = pix @ torch.linalg.inv(cam.K[0].double()).T
    c2w = cam.camera_to_world[0].double()
    d = d_cam @ c2w[:3, :3].T
    return c2w[:3, 3], d / d.norm(dim=-1, keepdim=True)


def exact_fresnel(cos_i: float, eta: float) -> float:
    """Unpolarised dielectric reflectance (float64, Snell's law written out)."""
    sin_t = eta * math.sqrt(max(0.0, 1.0 - cos_i * cos_i))
    if sin_t >= 1.0:
        return 1.0
    cos_t = math.sqrt(1.0 - sin_t * sin_t)
    n1, n2 = eta, 1.0
    rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
    rp = (n2 * cos_i - n1 * cos_t) / (n2 * cos_i + n1 * cos_t)
    return 0.5 * (rs * rs + rp * rp)


# -- the functions ---------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["exact", "schlick"])
def test_fresnel_at_normal_incidence_and_grazing(kind):
    one, zero = torch.ones(2, dtype=torch.float64), torch.zeros(2, dtype=torch.float64)
    eta = torch.tensor([1.0 / IOR, IOR], dtype=torch.float64)
    assert_close(fresnel(one, eta, kind), ((IOR - 1) / (IOR + 1)) ** 2, what="F at normal incidence")
    assert_close(fresnel(zero, eta, kind), 1.0, what="F at grazing")


def test_fresnel_exact_matches_snell_and_tir_past_the_critical_angle():
    cos = torch.linspace(0.0, 1.0, 101, dtype=torch.float64)
    for eta in (1.0 / IOR, IOR):
        got = fresnel(cos, torch.full_like(cos, eta))
        want = torch.tensor([exact_fresnel(c, eta) for c in cos.tolist()], dtype=torch.float64)
        assert_close(got, want, what=f"F(eta={eta:.3f})")
    cos_c = math.sqrt(1.0 - 1.0 / IOR**2)  # from below: total internal reflection for cos_i < cos_c
    c = torch.tensor([cos_c - 1e-6, cos_c + 1e-3], dtype=torch.float64)
    f = fresnel(c, torch.full_like(c, IOR))
    assert f[0] == 1.0 and f[1] < 1.0
    up = torch.stack([torch.sqrt(1 - c * c), c, torch.zeros_like(c)], 1)  # rising to the surface
    down = torch.tensor([[0.0, -1.0, 0.0]], dtype=torch.float64).expand(2, 3)  # its normal, facing the ray
    _, tir = refract(up, down, torch.full_like(c, IOR))
    assert tir.tolist() == [True, False]


def test_refract_obeys_snell():
    g = torch.Generator().manual_seed(1)
    d = torch.randn(200, 3, generator=g, dtype=torch.float64)
    d[:, 1] = -d[:, 1].abs() - 0.01
    d = d / d.norm(dim=1, keepdim=True)
    n = torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64).expand_as(d)
    t, tir = refract(d, n, torch.full((200,), 1.0 / IOR, dtype=torch.float64))
    assert not tir.any()
    sin_i = torch.sqrt(1 - d[:, 1] ** 2)
    sin_t = torch.sqrt(1 - t[:, 1] ** 2)
    assert_close(t.norm(dim=1), 1.0, what="|t|")
    assert_close(sin_t, sin_i / IOR, what="Snell")
    assert_close(reflect(d, n)[:, 1], -d[:, 1], what="reflected y")


@settings(max_examples=200, deadline=None)
@given(cos=st.floats(0.0, 1.0), ior=st.floats(1.0001, 4.0), below=st.booleans(), kind=st.sampled_from(["exact", "schlick"]))
def test_fresnel_finite_in_unit_interval(cos, ior, below, kind):
    eta = torch.tensor([ior if below else 1.0 / ior], dtype=torch.float32)
    f = fresnel(torch.tensor([cos], dtype=torch.float32), eta, kind)
    assert torch.isfinite(f).all() and 0.0 <= f.item() <= 1.0 + 1e-6


def test_rays_along_the_plane_never_hit_it():
    o = torch.tensor([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [0.0, -1.0, 0.0]])
    t = plane_hit(o, d, torch.zeros(4))
    assert t.tolist() == [math.inf, math.inf, 1.0, math.inf]
    assert beer(torch.tensor([[0.0, 0.5, 1.0]]), torch.tensor([math.inf])).tolist() == [[1.0, 0.0, 0.0]]


# -- renders ---------------------------------------------------------------------------------------


def water_scene(voxel_y, *, water=True, eye=(3.0, 4.0, -6.0), target=(0.5, -1.5, 0.5), size=32):
    scene = {
        "image": {"width": size, "height": size},
        "camera": {"eye": list(eye), "target": list(target), "fov_y": 50.0},
        "voxels": {"occupancy": {"grid": {"data": np.ones((2, 1, 2), np.uint8)}},
                   "cells": {"min": [0, voxel_y, 0], "max": [2, voxel_y + 1, 2]},
                   "materials": [[0.8, 0.6, 0.4]], "face_tones": [1.0, 1.0, 1.0], "ambient": [1.0, 1.0, 1.0]},
    }
    if water:
        scene["voxels"]["water"] = {"level": 0.0, "ior": IOR, "absorption": [50.0, 50.0, 50.0], "offset": 0.0,
                                    "waves": {"amplitude": 0.0}}
    return tv.load_scene(scene)


def test_flat_water_mirrors_a_voxel_with_fresnel_weight():
    """A voxel at y ∈ [2, 3] over flat water (its refraction absorbed, no sky) looks like the
    voxel mirrored to y ∈ [−3, −2] seen without water, times F; depth lies on the water."""
    a = tv.render(water_scene(2))
    b = tv.render(water_scene(-3, water=False))
    assert "voxels.water" in a.stats["passes"] and "voxels.water" not in b.stats["passes"]
    water = a.aovs["water"][0, 0] > 0
    assert water.float().mean() > 0.5
    seen = (a.radiance[0, 0] > 0) & water
    mirrored = (b.alpha[0, 0] > 0) & water
    assert seen.sum() >= 20, "the reflection is in view"
    assert (seen != mirrored).sum() <= 1, "the reflection sits at the mirrored position"
    _, d = pixel_rays(a)
    f = fresnel(d[..., 1].abs(), torch.full_like(d[..., 1], 1.0 / IOR))
    both = seen & mirrored
    expected = f[both][:, None].float() * b.radiance[0].permute(1, 2, 0)[both]
    assert_close(a.radiance[0].permute(1, 2, 0)[both], expected, atol=1e-5, what="reflected radiance")
    eye, d = pixel_rays(a)
    t = a.depth[0, 0].double() / (d @ (a.camera.world_to_camera[0, 2, :3].double()))  # planar -> distance
    y = eye[1] + t * d[..., 1]
    assert_close(y[water], 0.0, atol=1e-4, what="water depth on the plane y = 0")
    assert (a.aovs["water_floor_distance"] == 0).all(), "no floor under this water"


def test_camera_under_water_sees_snells_window():
    """Under flat water, no voxel in view: the sky only through Snell's window, (1 − F)·sky·
    e^{−a·t}; beyond the critical angle total internal reflection leaves black (absorbed)."""
    sky, a = np.array([0.6, 0.7, 0.8]), np.array([0.1, 0.2, 0.3])
    scene = tv.load_scene({
        "image": {"width": 31, "height": 29},
        "camera": {"eye": [0.0, -2.0, 0.0], "target": [0.0, -0.8, 3.0], "fov_y": 100.0},
        "sky": {"kind": "constant", "radiance": sky.tolist()},
        "voxels": {"occupancy": {"grid": {"data": [[[1]]]}}, "cells": {"min": [50, -50, 50], "max": [51, -49, 51]},
                   "water": {"level": 0.0, "ior": IOR, "absorption": a.tolist(), "waves": {"amplitude": 0.0}}},
    })
    out = tv.render(scene)
    _, d = pixel_rays(out)
    got = out.radiance[0].permute(1, 2, 0).double().numpy()
    want = np.zeros_like(got)
    for (r, c), dy in np.ndenumerate(d[..., 1].numpy()):
        if dy > 0:
            want[r, c] = (1.0 - exact_fresnel(dy, IOR)) * sky * np.exp(-a * 2.0 / dy)
    assert_close(torch.from_numpy(got), torch.from_numpy(want), atol=2e-5, what="under-water radiance")
    cos_c = math.sqrt(1.0 - 1.0 / IOR**2)
    up = d[..., 1].numpy()
    assert ((up > 0) & (up < cos_c - 1e-3)).sum() > 20 and (up > cos_c + 1e-3).sum() > 20, "both sides of the critical angle"
    assert (got[(up > 0) & (up < cos_c - 1e-3)] == 0).all()


@pytest.mark.parametrize("size", [(7, 5), (13, 11)])
def test_preset_finite_at_odd_sizes_and_rays_along_the_plane(size):
    out = tv.render(tv.load_scene(tv.preset("voxel-water", width=size[0], height=size[1]), {"image.spp": 2}))
    assert torch.isfinite(out.radiance).all() and torch.isfinite(out.depth).all()
    assert {"water", "water_floor_distance"} <= set(out.aovs)
    # a camera exactly on the water looking along it: the centre row's rays run in the plane
    level = tv.preset("voxel-water").voxels.water.level
    flat = tv.render(tv.load_scene(tv.preset("voxel-water", width=size[0], height=size[1]),
                                   {"camera.eye": [-20.0, level, -20.0], "camera.target": [0.0, level, 0.0]}))
    assert torch.isfinite(flat.radiance).all() and torch.isfinite(flat.depth).all()


def test_no_water_key_no_pass_and_water_leaves_other_pixels_bitwise():
    scene = tv.preset("voxel-carved-box", width=24, height=16)
    plan = make_plan(scene)
    assert "voxels.water" not in plan.names() and "water" not in plan.aovs
    plain = tv.render(scene)
    assert "voxels.water" not in plain.stats["passes"] and "water" not in plain.aovs
    wet = tv.render(tv.load_scene(scene, {"voxels.water": {"level": -50.0}}))
    dry = wet.aovs["water"][0, 0] == 0
    assert dry.float().mean() > 0.3
    assert torch.equal(wet.radiance[0][:, dry], plain.radiance[0][:, dry])
    assert torch.equal(wet.depth[0][:, dry], plain.depth[0][:, dry])


def test_waves_tilt_the_normal_with_time():
    x = torch.tensor([[0.3, 0.0, -1.2]])
    one = torch.ones(1)
    n0 = wave_normal(x, 0.05 * one, torch.tensor([[3.0, 2.0]]), torch.tensor([[1.0, 0.7]]), 0.0 * one)
    n1 = wave_normal(x, 0.05 * one, torch.tensor([[3.0, 2.0]]), torch.tensor([[1.0, 0.7]]), 1.0 * one)
    flat = wave_normal(x, 0.0 * one, torch.tensor([[3.0, 2.0]]), torch.tensor([[1.0, 0.7]]), 1.0 * one)
    assert_close(n0.norm(dim=1), 1.0) and not torch.equal(n0, n1)
    assert flat.tolist() == [[0.0, 1.0, 0.0]]


# -- the seed's water code on llvmpipe -------------------------------------------------------------


@pytest.mark.gl
@pytest.mark.skipif(gl_context() is None, reason="no GL context (moderngl/EGL) on this machine")
def test_seed_water_code_matches_llvmpipe():
    """The seed's wave normal, Schlick Fresnel (0.04 = F0 of ior 1.5), reflect and refract (from
    above, and from below with GLSL's zero vector under TIR) agree with water.py."""
    src = shadertoy_source((Path(tv.__file__).parent / "measure" / "voxel_water.glsl").read_text())
    w, h, time = 24, 20, 0.8
    gl = [run_fragment(src, w, h, uniforms={"uMode": m, "iTime": time})[::-1].reshape(-1, 4) for m in range(5)]  # row 0 = y 0
    v, u = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    x = torch.tensor(np.stack([(u - 0.5 * w) * 0.37, 0 * u, v * 0.29], -1).reshape(-1, 3), dtype=torch.float32)
    d = torch.from_numpy(gl[0][:, :3].copy())
    n_ = x.shape[0]
    n = wave_normal(x, torch.full((n_,), 0.05), torch.tensor([[3.0, 2.0]]).expand(n_, 2),
                    torch.tensor([[1.0, 0.7]]).expand(n_, 2), torch.full((n_,), time))
    assert_close(n, torch.from_numpy(gl[1][:, :3].copy()), atol=1e-5, what="wave normal")
    cos_i = (-(d * n).sum(1)).clamp(0.0, 1.0)
    assert_close(fresnel(cos_i, torch.full((n_,), 1.0 / 1.5), "schlick"), torch.from_numpy(gl[1][:, 3].copy()), atol=1e-5,
                 what="Schlick")
    assert_close(reflect(d, n), torch.from_numpy(gl[2][:, :3].copy()), atol=1e-5, what="reflect")
    t, _ = refract(d, n, torch.full((n_,), 1.0 / 1.33))
    assert_close(t, torch.from_numpy(gl[3][:, :3].copy()), atol=1e-5, what="refract into water")
    up = d * torch.tensor([1.0, -1.0, 1.0])
    t, tir = refract(up, -n, torch.full((n_,), 1.33))
    assert tir.any() and (~tir).any()
    assert_close(t, torch.from_numpy(gl[4][:, :3].copy()), atol=1e-5, what="refract out of water (TIR: 0)")


def test_water_no_ray_meets_is_not_a_pass_that_ran():
    out = tv.render(water_scene(2, eye=(0.0, 5.0, 0.0), target=(0.0, 10.0, 3.0), size=8))  # every ray rises
    assert "voxels.water" in out.stats["plan"]["passes"] and "voxels.water" not in out.stats["passes"]
    assert (out.aovs["water"] == 0).all()
