"""Physical shading against Mitsuba 3 on a small case of the parity scene (skipped without mitsuba).

Mitsuba's estimate is unbiased but noisy: at 1024 spp its relative RMSE against torchvol's float64
reference must sit at its own noise level (measured ~2.8% at 32×32) and its mean within 1%."""

import pytest

import torchvol as tv
from torchvol.measure.mitsuba import (
    puff_grid,
    relative_rmse,
    render_mitsuba,
    sigma_for,
    torchvol_scene,
)

mi = pytest.importorskip("mitsuba")


def test_single_scattering_agrees_with_mitsuba():
    grid = puff_grid(32)
    sigma = sigma_for(grid)
    ref = tv.render(torchvol_scene(grid, sigma, size=24, quality="reference", steps=256, shadow_steps=64))
    ours = ref.radiance[0].permute(1, 2, 0).numpy()
    theirs, _ = render_mitsuba(grid, sigma, size=24, spp=1024)
    err = relative_rmse(theirs, ours)
    ratio = theirs.mean() / ours.mean()
    assert err < 0.05 and abs(ratio - 1) < 0.01, f"Mitsuba vs torchvol: relative RMSE {err:.2%}, mean ratio {ratio:.4f}"
    # and the noise is noise: a second Mitsuba seed differs from the first about as much
    again, _ = render_mitsuba(grid, sigma, size=24, spp=1024, seed=1)
    assert relative_rmse(again, theirs) > 0.5 * err
