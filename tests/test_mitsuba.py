"""Physical shading against Mitsuba 3 on a small case of the parity scene (skipped without mitsuba).

Mitsuba's estimate is unbiased but noisy: at 1024 spp its relative RMSE against torchvol's float64
reference must sit at its own noise level (measured ~2.8% at 32×32) and its mean within 1%."""

import pytest

import torchvol as tv
from torchvol.measure.mitsuba import (
    EYE,
    FOV,
    IRRADIANCE,
    SUN,
    TARGET,
    puff_grid,
    relative_rmse,
    render_mitsuba,
    render_mitsuba_sphere,
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


def _sphere_scene(sigma_t: float, albedo: float, g: float, size: int) -> dict:
    return {"image": {"width": size, "height": size, "spp": 4}, "camera": {"eye": list(EYE), "target": list(TARGET), "fov_y": FOV},
            "lights": [{"direction": list(SUN), "intensity": IRRADIANCE, "shadow": {"steps": 32}}],
            "volumes": [{"bounds": {"sphere": {"center": [0, 0, 0], "radius": 1.0}}, "density": {"constant": 1.0},
                         "sigma_t": sigma_t, "albedo": albedo, "phase": {"hg": {"g": g}}}]}


@pytest.mark.slow
@pytest.mark.parametrize("bounces", [2, 63])
@pytest.mark.parametrize("medium", ["parity cloud", "HG sphere"])
def test_path_tracing_agrees_with_mitsuba_volpath(medium, bounces):
    """`[path]` against Mitsuba's `volpath` (max_depth = bounces + 1): the parity cloud (max
    optical depth 10, albedo 0.9, HG 0.8) and a homogeneous HG 0.8 sphere (σ_t·d = 5, albedo 0.9).
    Four independent renders of each give each image's mean and its noise, per pixel and over the
    image (estimated, not assumed). The means agree within four standard errors of their
    difference, and the pixels differ by what both noises explain."""
    import numpy as np

    size, seeds = 8, 4
    if medium == "parity cloud":
        grid = puff_grid(16)
        sigma = sigma_for(grid)
        scene = torchvol_scene(grid, sigma, size=size, spp=4)  # stratified sub-pixels: Mitsuba's box filter
        theirs = [render_mitsuba(grid, sigma, size=size, spp=1024, seed=k, max_depth=bounces + 1)[0] for k in range(seeds)]
    else:
        scene = _sphere_scene(2.5, 0.9, 0.8, size)
        theirs = [render_mitsuba_sphere(2.5, 0.9, 0.8, size=size, spp=1024, seed=k, max_depth=bounces + 1)[0]
                  for k in range(seeds)]
    scene["path"] = {"bounces": bounces, "samples": 32}
    ours = tv.render([scene] * seeds, seed=list(range(seeds))).radiance.double().permute(0, 2, 3, 1).numpy()
    theirs = np.stack(theirs).astype(np.float64)
    means = [x.mean(axis=(1, 2, 3)) for x in (ours, theirs)]
    gap = means[0].mean() - means[1].mean()
    error = float(np.sqrt(sum(m.var(ddof=1) / seeds for m in means)))
    assert abs(gap) <= 4.0 * error and error < 0.1 * means[1].mean(), (
        f"{medium}, bounces {bounces}: torchvol {means[0].mean():.5g}, Mitsuba {means[1].mean():.5g} (standard error {error:.2g})")
    noise = sum(x.var(axis=0, ddof=1).mean() / seeds for x in (ours, theirs))
    spread = ((ours.mean(axis=0) - theirs.mean(axis=0)) ** 2).mean()
    assert 0.4 < spread / noise < 2.5, f"{medium}, bounces {bounces}: pixels differ {spread / noise:.2f}× what the noise explains"
