"""Time to a relative RMSE of 1%: torchvol's `[path]` against Mitsuba 3's `volpath`, side by side.

    pip install mitsuba
    python tools/bench_path.py [--size 64] [--paths 64] [--passes 4] [--bounces 255]

The parity cloud (`torchvol.measure.mitsuba`: a 32³ fbm puff, max optical depth 10, albedo 0.9,
HG 0.8, one sun, no sky) with every order of scattering (torchvol `bounces` = B, Mitsuba
`max_depth` = B + 1). Each renderer renders `--passes` independent images of `--paths` paths a
pixel (torchvol: 4 stratified sub-samples × paths/4; Mitsuba: that many spp, box filter), each
timed warm (the median). One image's relative RMSE against the converged render is estimated
without rendering it (`debiased_relative_rmse`: the other passes' mean, their noise subtracted),
so its time to 1% is its time × (RMSE / 1%)², the RMSE falling as 1/√paths; the RMSE printed
is the root mean square of every pass's so estimated (their range beside it). Both renderers' means
are printed too: they must agree within their noise.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

import torchvol as tv
from torchvol.measure.mitsuba import (
    debiased_relative_rmse,
    puff_grid,
    render_mitsuba,
    sigma_for,
    torchvol_scene,
)


def torchvol_passes(grid, sigma, *, size: int, paths: int, passes: int, bounces: int) -> tuple[np.ndarray, float]:
    scene = torchvol_scene(grid, sigma, size=size, spp=4)
    scene["path"] = {"bounces": bounces, "samples": max(1, paths // 4)}
    tv.render(scene, seed=999)  # the kernel's build
    images, times = [], []
    for k in range(passes):
        start = time.perf_counter()
        out = tv.render(scene, seed=k)
        times.append(time.perf_counter() - start)
        images.append(out.radiance[0].permute(1, 2, 0).double().numpy())
    return np.stack(images), statistics.median(times)


def mitsuba_passes(grid, sigma, *, size: int, paths: int, passes: int, bounces: int) -> tuple[np.ndarray, float]:
    render_mitsuba(grid, sigma, size=4, spp=1, max_depth=bounces + 1)  # its scene's first load
    images, times = [], []
    for k in range(passes):
        image, seconds = render_mitsuba(grid, sigma, size=size, spp=paths, seed=k, max_depth=bounces + 1)
        images.append(image.astype(np.float64))
        times.append(seconds)
    return np.stack(images), statistics.median(times)


def pass_rmse(images: np.ndarray) -> list[float]:
    """Each pass's relative RMSE against the converged render, estimated from the other passes
    (`debiased_relative_rmse`, P images (P, H, W, C)): one pass's alone varied by ±6% between runs,
    their root mean square by less."""
    out = []
    for k in range(images.shape[0]):
        r = debiased_relative_rmse(images[k], np.delete(images, k, axis=0))
        out.append(r["rmse"] if r["rmse"] > 0 else r["raw"])
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--paths", type=int, default=64, help="paths a pixel in each pass")
    parser.add_argument("--passes", type=int, default=4)
    parser.add_argument("--bounces", type=int, default=255)
    parser.add_argument("--optical-depth", type=float, default=10.0, help="the cloud's largest optical depth")
    args = parser.parse_args()
    grid = puff_grid(32)
    sigma = sigma_for(grid, args.optical_depth)
    print(f"parity cloud (max optical depth {args.optical_depth:g}), {args.size}², every order up to {args.bounces} scatterings, {args.passes} passes of "
          f"{args.paths} paths a pixel, torch threads {torch.get_num_threads()}\n")
    print("| renderer | one pass s | mean | relative RMSE of a pass (each pass's range) | time to 1% s |")
    print("| --- | ---: | ---: | ---: | ---: |")
    runs = (("torchvol [path]", torchvol_passes), ("Mitsuba 3 volpath scalar_rgb", mitsuba_passes))
    for name, run in runs:
        images, seconds = run(grid, sigma, size=args.size, paths=args.paths, passes=args.passes, bounces=args.bounces)
        each = pass_rmse(images)
        rmse = float(np.sqrt(np.mean(np.square(each))))
        print(f"| {name} | {seconds:.2f} | {images.mean():.5f} | {rmse:.2%} ({min(each):.2%}–{max(each):.2%}) "
              f"| {seconds * (rmse / 0.01) ** 2:.0f} |", flush=True)


if __name__ == "__main__":
    main()
