"""The heterogeneous-medium parity scene of torchvol and Mitsuba 3 (issue: physical parity).

A 64³ fbm cloud puff in the box [-1, 1]³ (max optical depth `max_optical_depth` along the view
axis), albedo 0.9, HG g = 0.8, one sun, no sky, fov 40°, camera on −z. Conventions bridged here:
Mitsuba's `directional.direction` is where light travels (minus ours); its `cube` spans [-1, 1]³;
`gridvolume` is cell-centred with clamp (as torchvol's grid); the medium's container has a `null`
BSDF; `volpath` with max_depth = 2 is exactly single scattering; its film averages over the pixel
area (box filter here), so torchvol renders with stratified spp to match.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from ..noise import lattice as noise

EYE, TARGET, FOV = (0.0, 0.2, -4.0), (0.0, 0.0, 0.0), 40.0
SUN = tuple((np.array([0.5, 0.8, -0.3]) / np.linalg.norm([0.5, 0.8, -0.3])).tolist())
IRRADIANCE = 3.0


def puff_grid(n: int = 64, seed: int = 0) -> np.ndarray:
    """Cell-centred density (n, n, n) [k, j, i] in [0, 1]: fbm value noise thinned out radially."""
    c = (torch.arange(n, dtype=torch.float64) + 0.5) / n * 2 - 1
    z, y, x = torch.meshgrid(c, c, c, indexing="ij")
    p = torch.stack([x, y, z], -1).reshape(-1, 3)
    f = noise.fbm(p * 2.5 + 3.1, lambda q: noise.value_noise(q, seed=seed), octaves=4)
    d = (1.4 * f + 0.35 - 1.3 * p.norm(dim=1)).clamp_min(0).reshape(n, n, n)
    return (d / d.max()).numpy()


def sigma_for(grid: np.ndarray, max_optical_depth: float = 10.0) -> float:
    """σ_t scale giving `max_optical_depth` along the densest line parallel to z (box size 2)."""
    column = grid.sum(axis=0) * (2.0 / grid.shape[0])  # ∫ density dz per (j, i)
    return max_optical_depth / float(column.max())


def torchvol_scene(grid: np.ndarray, sigma: float, *, size: int, spp: int = 16, **march) -> dict:
    """The comparison's scene as a torchvol scene dict: `grid` (n, n, n) density times `sigma` in
    the box [-1, 1]³, a sun, a `size`² image at `spp`; `march` the scene's march keys
    (`shadow_steps` the light's shadow steps)."""
    return {
        "image": {"width": size, "height": size, "spp": spp},
        "camera": {"eye": list(EYE), "target": list(TARGET), "fov_y": FOV},
        "lights": [{"direction": list(SUN), "intensity": IRRADIANCE, "shadow": {"steps": march.pop("shadow_steps", 32)}}],
        "volumes": [{"bounds": {"box": {"min": [-1, -1, -1], "max": [1, 1, 1]}}, "density": {"grid": {"data": grid}},
                     "sigma_t": sigma, "albedo": 0.9, "phase": {"hg": {"g": 0.8}}}],
        "march": march,
    }


def _render(cloud: dict, *, size: int, spp: int, variant: str, seed: int, max_depth: int) -> tuple[np.ndarray, float]:
    """Mitsuba's render (H, W, 3) of the comparison's camera and sun and the medium `cloud` (a
    shape dict, its `interior` the medium) and its wall time: `volpath` with `max_depth` (2:
    single scattering; B + 1: light scattered at most B times, torchvol's `[path].bounces` = B;
    no roulette before 10 × max_depth)."""
    import mitsuba as mi

    mi.set_variant(variant)
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "volpath", "max_depth": max_depth, "rr_depth": 10 * max_depth},
        "sensor": {"type": "perspective", "fov": FOV, "fov_axis": "y",
                   "to_world": mi.ScalarTransform4f().look_at(origin=list(EYE), target=list(TARGET), up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"},
                            "pixel_format": "rgb"},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "sun": {"type": "directional", "direction": [-v for v in SUN], "irradiance": {"type": "rgb", "value": [IRRADIANCE] * 3}},
        "cloud": cloud(mi) if callable(cloud) else cloud,
    })
    start = time.perf_counter()
    image = np.array(mi.render(scene, seed=seed))[..., :3]
    return image, time.perf_counter() - start


def render_mitsuba(grid: np.ndarray, sigma: float, *, size: int, spp: int, variant: str = "scalar_rgb",
                   seed: int = 0, max_depth: int = 2) -> tuple[np.ndarray, float]:
    """Mitsuba's render (H, W, 3) of the parity cloud and its wall time in seconds (`_render`)."""
    def cloud(mi):
        grid_volume = mi.VolumeGrid(np.ascontiguousarray(grid[..., None], dtype=np.float32))
        return {"type": "cube", "bsdf": {"type": "null"},
                "interior": {"type": "heterogeneous", "albedo": 0.9, "scale": sigma,
                             "sigma_t": {"type": "gridvolume", "grid": grid_volume,
                                         "to_world": mi.ScalarTransform4f().translate([-1, -1, -1]).scale(2.0)},
                             "phase": {"type": "hg", "g": 0.8}}}

    return _render(cloud, size=size, spp=spp, variant=variant, seed=seed, max_depth=max_depth)


def render_mitsuba_sphere(sigma_t: float, albedo: float, g: float, *, size: int, spp: int, variant: str = "scalar_rgb",
                          seed: int = 0, max_depth: int = 2) -> tuple[np.ndarray, float]:
    """Mitsuba's render (H, W, 3) of a homogeneous HG `g` sphere of radius 1 at the origin (σ_t,
    albedo) under the comparison's sun, and its wall time (`_render`)."""
    cloud = {"type": "sphere", "radius": 1.0, "bsdf": {"type": "null"},
             "interior": {"type": "homogeneous", "albedo": albedo, "sigma_t": sigma_t, "phase": {"type": "hg", "g": g}}}
    return _render(cloud, size=size, spp=spp, variant=variant, seed=seed, max_depth=max_depth)


def relative_rmse(image: np.ndarray, reference: np.ndarray) -> float:
    """RMSE of `image` against `reference` (same shape, e.g. (H, W, C)) over the reference's root
    mean square."""
    return float(np.sqrt(((image - reference) ** 2).mean()) / np.sqrt((reference**2).mean()))


def debiased_relative_rmse(image: np.ndarray, passes: np.ndarray) -> dict[str, float]:
    """The relative RMSE of `image` (H, W, C) against the *converged* render that independent
    Monte Carlo `passes` (P, H, W, C) average to, without rendering it: the mean of the passes
    carries noise of variance v per value (their sample variance / P, averaged over the image),
    which adds v to the mean squared difference, so MSE − v estimates the squared difference to the
    converged render, unbiased. Its standard error (difference b² = MSE − v, N = H·W pixels; the
    channels of a grey scene are not independent) is √((2v² + 4b²v)/N + 2v²/(N(P − 1))): the
    noise's own square and its cross term with the difference, and the spread of v's estimate.
    Returns {"rmse": the estimate, "low", "high": two standard errors either side (clamped at 0),
    "noise": √v, "raw": the plain relative RMSE against the mean of the passes}, all relative to the
    converged render's RMS value."""
    count = passes.shape[0]
    mean = passes.mean(axis=0)
    v = float((passes.var(axis=0, ddof=1) / count).mean())
    mse = float(((image - mean) ** 2).mean())
    b2 = mse - v
    n = image.shape[0] * image.shape[1]
    se = float(np.sqrt((2 * v * v + 4 * max(b2, 0.0) * v) / n + 2 * v * v / (n * (count - 1))))
    rms = float(np.sqrt((mean**2).mean() - v))

    def rel(x: float) -> float:
        return float(np.sqrt(max(x, 0.0)) / rms)

    return {"rmse": rel(b2), "low": rel(b2 - 2 * se), "high": rel(b2 + 2 * se), "noise": rel(v), "raw": rel(mse)}
