"""Tonemaps, vignette and fog (post.py) against their formulas."""

import math

import torch
from conftest import assert_close

from torchvol import post


def test_smoothstep_is_glsl():
    x = torch.tensor([-1.0, 0.15, 0.5, 1.1, 3.0], dtype=torch.float64)
    t = ((x - 0.15) / 0.95).clamp(0, 1)
    assert_close(post.smoothstep(0.15, 1.1, x), t * t * (3 - 2 * t), what="smoothstep")


def test_tonemaps_are_monotone_and_bounded():
    x = torch.logspace(-4, 4, 500, dtype=torch.float64)
    for fn in (post.reinhard, post.aces):
        y = fn(x)
        assert (y.diff() >= -1e-12).all() and y.min() >= 0 and y.max() <= 1, fn.__name__
    assert_close(post.reinhard(torch.tensor([1.0], dtype=torch.float64)), torch.tensor([0.5], dtype=torch.float64))


def test_tonemaps_of_huge_radiance_are_white_not_nan():
    """Radiance up to float32's largest finite value (a fuzz scene's terrain of colour 1e12 gave 3e24,
    whose square overflowed ACES's fit to inf/inf) maps to 1; below the fit's knee, as before."""
    x = torch.tensor([3e24, 1e30, 3.4e38, 1e19], dtype=torch.float32)
    for fn in (post.reinhard, post.aces):
        y = fn(x)
        assert torch.isfinite(y).all() and bool((y == 1.0).all()), (fn.__name__, y.tolist())
    assert bool((post.aces(torch.tensor([7.3, 1e4])) == 1.0).all())
    low = torch.linspace(0.0, 7.0, 50, dtype=torch.float64)
    assert_close(post.aces(low), ((low * (2.51 * low + 0.03)) / (low * (2.43 * low + 0.59) + 0.14)).clamp(0, 1), what="aces")


def test_vignette_darkens_corners_not_the_centre():
    image = torch.ones(1, 3, 41, 61)
    v = post.vignette(image, 1.0)
    u, w = 0.5 / 61, 0.5 / 41  # the corner pixel's centre in [0, 1]²
    corner = 0.25 + 0.75 * (16 * u * (1 - u) * w * (1 - w)) ** 0.1
    assert v[0, 0, 20, 30] > 0.99 and abs(v[0, 0, 0, 0].item() - corner) < 1e-6
    assert torch.equal(post.vignette(image, 0.0), image)


def test_distance_fog_blends_by_extinction_and_spares_misses():
    radiance = torch.zeros(1, 3, 1, 3, dtype=torch.float64)
    distance = torch.tensor([[[[0.0, 1.0, 100.0]]]], dtype=torch.float64)
    out = post.distance_fog(radiance, distance, torch.ones(1, 3, dtype=torch.float64), torch.tensor([0.5], dtype=torch.float64))
    expected = torch.tensor([0.0, 1 - math.exp(-0.5), 1.0], dtype=torch.float64)
    assert_close(out[0, 0, 0], expected, what="fog amount")
