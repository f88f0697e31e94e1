"""More hard cases: degenerate thin bounds, huge distances, fbm at extreme frequencies and octave
counts, float32 against float64, and voxel rays along axes and through exact ties — under the
invariants: finite output, alpha and image in [0, 1], depth ≥ 0."""

import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import torchvol as tv
from torchvol.noise import lattice as noise

pytestmark = pytest.mark.usefixtures("one_thread")
SETTINGS = settings(max_examples=20, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))


def check(out, what=""):
    for name in ("image", "radiance", "depth", "alpha"):
        value = getattr(out, name)
        bad = ~torch.isfinite(value)
        assert not bad.any(), f"{what}{name}: non-finite at {tuple(bad.nonzero()[0].tolist())}"
    for name, value in out.aovs.items():
        assert torch.isfinite(value).all(), f"{what}aov {name} not finite"
    assert out.alpha.min() >= 0 and out.alpha.max() <= 1 + 1e-6, f"{what}alpha out of [0, 1]"
    assert out.image.min() >= 0 and out.image.max() <= 1, f"{what}image out of [0, 1]"
    assert out.depth.min() >= 0, f"{what}negative depth"


@SETTINGS
@given(thickness=st.sampled_from([1e-9, 1e-6, 1e-3]), sigma=st.sampled_from([0.0, 1.0, 1e7]),
       axis=st.sampled_from([0, 1, 2]), closed=st.booleans())
def test_degenerate_thin_boxes(thickness, sigma, axis, closed):
    lo, hi = [-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]
    lo[axis], hi[axis] = -thickness / 2, thickness / 2
    scene = {"image": {"width": 9, "height": 7}, "camera": {"eye": [0.4, 0.7, -2.0], "fov_y": 50},
             "lights": [{"direction": [0.2, 1.0, -0.3]}],
             "volumes": [{"bounds": {"box": {"min": lo, "max": hi}}, "sigma_t": sigma}],
             "march": {"closed_form": closed, "steps": 6}}
    out = tv.render(scene)
    check(out, f"thin {thickness} axis {axis}: ")
    # a slab of thickness d seen at any angle: alpha ≤ 1 − e^{−σ d / cos} stays tiny unless σ is huge
    if sigma * thickness < 1e-6:
        assert out.alpha.max() < 1e-4


@SETTINGS
@given(distance=st.sampled_from([1e3, 1e5, 1e7]), dtype=st.sampled_from([torch.float32, torch.float64]))
def test_huge_distances(distance, dtype):
    """A unit sphere seen from very far with a narrow field of view, and a slab reaching far."""
    fov = math.degrees(2 * math.atan(2.0 / distance))
    scene = {"image": {"width": 8, "height": 8}, "camera": {"eye": [0.0, 0.0, -distance], "fov_y": fov},
             "volumes": [{"bounds": {"sphere": {"radius": 1.0}}, "sigma_t": 5.0}], "march": {"steps": 4}}
    out = tv.render(scene, dtype=dtype)
    check(out, f"distance {distance}: ")
    # float32 resolves a unit sphere up to ~1e5 away (its ulp there is 0.008); float64 far beyond
    if dtype == torch.float64 or distance <= 1e5:
        assert out.alpha[0, 0, 3:5, 3:5].min() > 0.9, "the sphere at the centre vanished"
    slab = {"image": {"width": 8, "height": 8}, "camera": {"eye": [0.0, 0.5, 0.0], "target": [1.0, 0.5, 0.0], "fov_y": 10},
            "volumes": [{"bounds": {"slab": {"y_min": 0.0, "y_max": 1.0}}, "sigma_t": 1e-9}],
            "march": {"closed_form": False, "steps": 4, "max_distance": distance}}
    check(tv.render(slab, dtype=dtype), f"slab to {distance}: ")


@SETTINGS
@given(octaves=st.integers(1, 8), frequency=st.sampled_from([1e-3, 1.0, 1e3, 1e5]),
       kind=st.sampled_from(["value", "perlin", "worley"]))
def test_fbm_extreme_frequencies_and_octaves(octaves, frequency, kind):
    scene = {"image": {"width": 8, "height": 6}, "camera": {"eye": [0.0, 0.3, -2.5], "fov_y": 45},
             "lights": [{"direction": [0.0, 1.0, 0.0], "shadow": {"steps": 2}}],
             "volumes": [{"bounds": {"sphere": {"radius": 1.0}}, "sigma_t": 4.0,
                          "density": {"fbm": {"octaves": octaves, "frequency": frequency, "noise": kind}}}],
             "march": {"steps": 6}}
    check(tv.render(scene), f"fbm {kind} x{octaves} @ {frequency}: ")


@SETTINGS
@given(sigma=st.sampled_from([0.0, 1e-3, 1.0, 1e3, 1e7]), frequency=st.sampled_from([1e-3, 1.0, 30.0]),
       g=st.sampled_from([-0.999, 0.0, 0.999]), inside=st.booleans(), tolerance=st.sampled_from([1e-1, 1e-3]))
def test_error_controlled_march(sigma, frequency, g, inside, tolerance):
    """`march.tolerance` on fbm (its signed value, islands, the light's curvature) from σ = 0 to 1e7,
    at g near ±1, with the camera inside the cloud or outside it."""
    scene = {"image": {"width": 6, "height": 5}, "camera": {"eye": [0.1, 0.2, -0.3 if inside else -2.5], "fov_y": 60},
             "lights": [{"direction": [0.3, 1.0, -0.2], "intensity": 3.0, "shadow": {"steps": 3}}],
             "volumes": [{"bounds": {"sphere": {"radius": 1.0}}, "sigma_t": sigma, "phase": {"hg": {"g": g}},
                          "density": {"fbm": {"octaves": 3, "frequency": frequency, "radial": 0.5}}}],
             "march": {"tolerance": tolerance}}
    out = tv.render(scene)
    check(out, f"tolerance {tolerance}, σ {sigma}, frequency {frequency}, g {g}: ")
    assert math.isfinite(out.stats["error_estimate"])


@pytest.mark.parametrize("name", ["cloud-puff", "homogeneous-box", "voxel-terrain"])
def test_float32_within_tolerance_of_float64(name):
    scene = tv.preset(name, width=16, height=12)
    if name == "cloud-puff":
        scene = tv.load_scene(scene, {"march.steps": 12, "lights[0].shadow.steps": 3})
    a, b = tv.render(scene, dtype=torch.float32), tv.render(scene, dtype=torch.float64)
    alpha_err = (a.alpha - b.alpha).abs().max().item()
    rad_err = ((a.radiance - b.radiance).abs() / b.radiance.abs().clamp_min(1e-3)).max().item()
    assert alpha_err < 1e-4, f"{name}: alpha float32 vs float64 differs by {alpha_err:.2e}"
    assert rad_err < 1e-3, f"{name}: radiance float32 vs float64 differs by {rad_err:.2e} (relative)"


@SETTINGS
@given(axis=st.sampled_from([0, 1, 2]), sign=st.sampled_from([-1.0, 1.0]), offset=st.sampled_from([0.0, 0.5, 1.0]))
def test_voxel_rays_along_axes_and_through_edges(axis, sign, offset):
    """Cameras on grid lines (offset 0 or 1: exactly on cell faces) looking straight along an axis:
    every ray is axis-parallel or passes through edges and corners (exact DDA ties)."""
    data = np.zeros((6, 6, 6), dtype=np.uint8)
    data[1:5, 1:5, 1:5] = 1
    eye = [offset, offset, offset]
    eye[axis] = -12.0 * sign
    target = list(eye)
    target[axis] = 0.0
    up = [0.0, 1.0, 0.0] if axis != 1 else [0.0, 0.0, 1.0]
    scene = {"image": {"width": 7, "height": 7}, "camera": {"eye": eye, "target": target, "up": up, "fov_y": 40},
             "lights": [{"direction": [0.3, 0.8, -0.5]}],
             "voxels": {"cells": {"min": [-3, -3, -3], "max": [3, 3, 3]}, "occupancy": {"grid": {"data": data}},
                        "ao": {"gamma": 0.5}, "shadow": {"steps": 16}}}
    out = tv.render(scene)
    check(out, f"axis {axis} sign {sign} offset {offset}: ")
    assert out.alpha[0, 0, 3, 3] == 1, "the ray through the image centre missed the block"
    for name in ("normal", "uv", "ao"):
        assert name in out.aovs


def test_noise_is_finite_for_huge_coordinates():
    p = torch.tensor([[1e9, -1e9, 3e8], [1e15, 2.0, -7e14], [0.0, 0.0, 0.0]], dtype=torch.float64)
    for fn in (noise.value_noise, noise.perlin_noise, noise.worley_noise):
        value = fn(p, seed=3)
        assert torch.isfinite(value).all() and value.abs().max() <= 1.1, fn.__name__
