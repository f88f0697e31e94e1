"""Physical parity with Mitsuba 3, and time to accuracy: both renderers' error-vs-time curves in one run.

    pip install mitsuba
    python tools/compare_mitsuba.py [--size 32] [--spp 256,1024,4096] [--variant scalar_rgb]
                                    [--target-size 256] [--stride 4]
    python tools/compare_mitsuba.py --converge 16 [--pass-spp 65536] [--torchvol-spp 1024] [--size 32]
    # llvm_ad_rgb needs an LLVM newer than Debian 12's 15 (which crashes it):
    apt-get install libllvm19 && export DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM-19.so

The scene is `torchvol.measure.mitsuba` (64³ cloud puff, max optical depth 10, albedo 0.9, HG 0.8,
one sun, no sky, fov 40°). Three tables:

1. Parity (`--size`², pixel-area averages as Mitsuba's box-filtered film gives them): Mitsuba's
   relative RMSE against the exact float64 reference (averaged over 64 jittered strata per pixel)
   falling as 1/√spp, with a mean ratio → 1, is what shows the two renderers agree; torchvol with
   64 stratified samples per pixel converges to the same averages.
2. Quality levels (`--target-size`², pixel centres) against the exact reference.
3. Time to accuracy (`--target-size`², rays through pixel centres): torchvol settings against the
   exact float64 reference (`volume.exact`, integrated between the grid's interpolation planes), on
   every `--stride`-th pixel each way. Times are medians of 3 renders.

`--converge PASSES` instead compares torchvol's levels directly with a converged Mitsuba render
(pixel averages at `--size`², PASSES × `--pass-spp` spp, torchvol at `--torchvol-spp` strata, 0:
each level's own spp): the relative RMSE against the passes' mean, and that RMSE less the mean's
own noise, estimated from the spread of the passes (`debiased_relative_rmse`), which is the RMSE
against the render the passes converge to. `--torchvol-centres K` renders torchvol at K·size
through pixel centres and averages K×K blocks: the same pixel-area averages as Mitsuba's film,
without the jitter noise of the levels' own spp. At 256², 64 passes of 1024 spp take ~52 minutes
on 2 cores (docs/PARITY.md):
    python tools/compare_mitsuba.py --converge 64 --pass-spp 1024 --size 256 --torchvol-centres 2 \
        --variant llvm_ad_rgb --cache mitsuba-passes
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import torch

import torchvol as tv
from torchvol.light.phase import henyey_greenstein
from torchvol.measure.mitsuba import (
    IRRADIANCE,
    SUN,
    debiased_relative_rmse,
    puff_grid,
    relative_rmse,
    render_mitsuba,
    sigma_for,
    torchvol_scene,
)
from torchvol.renderer.executor import camera_for
from torchvol.schema.batch import stack
from torchvol.volume.exact import grid_single_scatter

F64 = torch.float64


def torchvol_image(grid: np.ndarray, sigma: float, *, size: int, spp: int | None, quality: str, shadow_steps: int | None = None) -> tuple[np.ndarray, float]:
    """torchvol's radiance (H, W, 3) of the scene at a quality level, and its wall time in seconds
    (`spp`, `shadow_steps` None: the level's)."""
    start = time.perf_counter()
    out = tv.render(torchvol_scene(grid, sigma, size=size, spp=spp, shadow_steps=shadow_steps, quality=quality))
    return out.radiance[0].permute(1, 2, 0).numpy(), time.perf_counter() - start


def parity(grid: np.ndarray, sigma: float, size: int, spps: list[int], variant: str) -> None:
    """Pixel averages: Mitsuba's and torchvol's (64 stratified samples) against the exact reference
    averaged over 8×8 jittered strata."""
    exact, _, seconds = exact_rays(grid, sigma, size, spp=64)
    ref = exact.reshape(size, size, 64).mean(-1).numpy()[..., None]
    print(f"## Parity, {size}×{size} pixel averages, σ scale {sigma:.3f}; error = relative RMSE against the exact "
          f"float64 reference averaged over 64 jittered strata per pixel ({seconds:.1f} s)\n")
    print("| renderer | setting | time (s) | relative RMSE | mean / reference mean |")
    print("| --- | --- | ---: | ---: | ---: |")
    for quality in ("default", "high"):
        img, seconds = torchvol_image(grid, sigma, size=size, spp=64, quality=quality, shadow_steps=32)
        print(f"| torchvol | {quality}, 64 spp | {seconds:.2f} | {relative_rmse(img, ref):.4%} | {img.mean() / ref.mean():.4f} |", flush=True)
    for spp in spps:
        img, seconds = render_mitsuba(grid, sigma, size=size, spp=spp, variant=variant)
        print(f"| Mitsuba 3 ({variant}) | {spp} spp | {seconds:.2f} | {relative_rmse(img, ref):.4%} | {img.mean() / ref.mean():.4f} |", flush=True)


def converged(grid: np.ndarray, sigma: float, size: int, passes: int, per_pass: int, variant: str,
              torchvol_spp: int | None, cache: Path | None, centres: int = 0) -> None:
    """torchvol's levels (at `torchvol_spp` stratified samples per pixel, or each level's own spp
    when None; or, with `centres` k > 0, rendered at k·size through pixel centres and averaged over
    k×k blocks: the k×k midpoint rule of each pixel's area average, deterministic) against the
    render that `passes` Mitsuba renders of `per_pass` spp (seeds 0, 1, ...) converge to: the
    relative RMSE against their mean, and that RMSE less the mean's own noise
    (`debiased_relative_rmse`, with two standard errors either side). Passes are kept in `cache`
    (a folder) when given, so a re-run renders only what is missing."""
    def pixel_averages(quality: str) -> tuple[np.ndarray, float]:
        if not centres:
            return torchvol_image(grid, sigma, size=size, spp=torchvol_spp, quality=quality)
        fine, seconds = torchvol_image(grid, sigma, size=centres * size, spp=1, quality=quality)
        return fine.reshape(size, centres, size, centres, 3).mean(axis=(1, 3)), seconds

    # torchvol first, so that Mitsuba's passes do not slow it
    results = [(quality, *pixel_averages(quality)) for quality in ("default", "high", "reference")]
    images, seconds = [], 0.0
    for seed in range(passes):
        path = None if cache is None else cache / f"mitsuba-{size}-{variant}-{per_pass}spp-seed{seed}.npy"
        if path is not None and path.is_file():
            images.append(np.load(path))
            continue
        image, took = render_mitsuba(grid, sigma, size=size, spp=per_pass, variant=variant, seed=seed)
        images.append(image)
        seconds += took
        if path is not None:
            cache.mkdir(parents=True, exist_ok=True)
            np.save(path, image)
    images = np.stack(images)
    mitsuba = images.mean(axis=0)
    errors = [debiased_relative_rmse(image, images) for _, image, _ in results]
    if centres:
        strata = f"{centres}×{centres} pixel centres of a {centres * size}² render per pixel"
    else:
        strata = "each level's own spp" if torchvol_spp is None else f"{torchvol_spp} stratified samples per pixel"
    print(f"\n## Against a converged Mitsuba render, {size}×{size} pixel averages: Mitsuba 3 ({variant}) at "
          f"{passes * per_pass:,} spp ({passes} passes; {seconds:.0f} s rendered in this run; the mean's own noise ≈ "
          f"{errors[0]['noise']:.4%}); torchvol at {strata}\n")
    print("| torchvol level | time (s) | relative RMSE against the passes' mean | against the converged render (± 2 s.e.) | mean / Mitsuba mean |")
    print("| --- | ---: | ---: | ---: | ---: |")
    for (quality, image, took), e in zip(results, errors):
        print(f"| {quality} | {took:.1f} | {e['raw']:.4%} | {e['rmse']:.4%} ({e['low']:.4%} – {e['high']:.4%}) | "
              f"{image.mean() / mitsuba.mean():.4f} |", flush=True)


def levels(grid: np.ndarray, sigma: float, size: int, stride: int) -> None:
    """Each quality level, one ray through each pixel centre, against the exact reference."""
    exact, mask = exact_table(grid, sigma, size, stride, "Quality levels", ["level", "time (s)", "relative RMSE", "mean / reference mean"])
    for quality in ("draft", "default", "high", "reference"):
        image, seconds = torchvol_image(grid, sigma, size=size, spp=1, quality=quality)
        got = torch.from_numpy(image[..., 0]).reshape(-1).double()[mask]
        print(f"| {quality} | {seconds:.2f} | {relative_rmse(got.numpy(), exact.numpy()):.4%} | {float(got.mean() / exact.mean()):.4f} |", flush=True)


def exact_rays(grid: np.ndarray, sigma: float, size: int, *, spp: int = 1, stride: int = 1) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Exact radiance of the scene's rays (pixel centres for spp = 1, jittered strata otherwise) on
    every `stride`-th pixel each way, the ray mask, and the time it took."""
    camera = camera_for(stack([tv.load_scene(torchvol_scene(grid, sigma, size=size, spp=1))], dtype=F64))
    rays = camera.rays(spp=spp, generator=None if spp == 1 else torch.Generator().manual_seed(0))
    mask = ((rays.pixel[:, 0] % stride) == stride // 2) & ((rays.pixel[:, 1] % stride) == stride // 2)
    box = -torch.ones(3, dtype=F64), torch.ones(3, dtype=F64)
    start = time.perf_counter()
    radiance, _ = grid_single_scatter(torch.as_tensor(grid, dtype=F64), *box, rays.origins[mask], rays.directions[mask],
                                      sigma_t=sigma, albedo=0.9, sun=torch.tensor(SUN, dtype=F64), irradiance=IRRADIANCE,
                                      phase=lambda c: henyey_greenstein(c, torch.full_like(c, 0.8)))
    return radiance, mask, time.perf_counter() - start


def exact_table(grid: np.ndarray, sigma: float, size: int, stride: int, title: str, columns: list[str]) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact radiance at pixel centres on every `stride`-th pixel and its mask; prints the table's
    heading and header row (the first column left-aligned, the others right-aligned)."""
    exact, mask, seconds = exact_rays(grid, sigma, size, stride=stride)
    print(f"\n## {title}, {size}×{size}, rays through pixel centres; error = relative RMSE against the exact "
          f"reference on {int(mask.sum())} pixels ({seconds:.1f} s)\n")
    print("| " + " | ".join(columns) + " |")
    print("| --- |" + " ---: |" * (len(columns) - 1))
    return exact, mask


def time_to_accuracy(grid: np.ndarray, sigma: float, size: int, stride: int) -> None:
    exact, mask = exact_table(grid, sigma, size, stride, "Time to accuracy",
                              ["shadows", "steps", "time (s), median of 3", "relative RMSE", "density evals", "march steps"])
    settings = [("march", n, n // 2) for n in (32, 64, 128)] + [("grid", n, None) for n in (48, 64, 96, 128, 192)]
    for method, steps, shadow_steps in settings:
        scene = torchvol_scene(grid, sigma, size=size, spp=1, steps=steps, shadow_steps=shadow_steps or 16)
        scene["lights"][0]["shadow"].update(method=method, resolution=128)
        times = []
        for _ in range(3):
            start = time.perf_counter()
            out = tv.render(scene)
            times.append(time.perf_counter() - start)
        got = out.radiance[0, 0].reshape(-1).double()[mask]
        err = float(((got - exact) ** 2).mean().sqrt() / (exact**2).mean().sqrt())
        label = f"march, {shadow_steps} steps" if method == "march" else "grid, resolution 128"
        print(f"| {label} | {steps} | {statistics.median(times):.3f} | {err:.4%} | {out.stats['density_evals']:,} | {out.stats['march_steps']:,} |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=32)
    parser.add_argument("--spp", default="256,1024,4096", help="Mitsuba sample counts; empty: skip the parity table")
    parser.add_argument("--variant", default="scalar_rgb")
    parser.add_argument("--target-size", type=int, default=256)
    parser.add_argument("--stride", type=int, default=4)
    parser.add_argument("--converge", type=int, default=0, metavar="PASSES",
                        help="also compare the levels with a Mitsuba render of PASSES × --pass-spp spp at --size² (then only that)")
    parser.add_argument("--pass-spp", type=int, default=65536)
    parser.add_argument("--torchvol-spp", type=int, default=1024, help="0: each level's own spp")
    parser.add_argument("--cache", type=Path, default=None, help="folder that keeps Mitsuba's passes between runs")
    parser.add_argument("--torchvol-centres", type=int, default=0, metavar="K",
                        help="torchvol at K·size through pixel centres, averaged K×K (instead of --torchvol-spp)")
    args = parser.parse_args()
    grid = puff_grid()
    sigma = sigma_for(grid)
    if args.converge:
        converged(grid, sigma, args.size, args.converge, args.pass_spp, args.variant, args.torchvol_spp or None, args.cache,
                  args.torchvol_centres)
        return
    if args.spp:
        parity(grid, sigma, args.size, [int(s) for s in args.spp.split(",")], args.variant)
    levels(grid, sigma, args.target_size, args.stride)
    time_to_accuracy(grid, sigma, args.target_size, args.stride)


if __name__ == "__main__":
    main()
