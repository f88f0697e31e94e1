"""Error of Wrenninge's multiple-scattering octaves against Mitsuba 3's path-traced multiple
scattering, on a homogeneous sphere lit by one sun.

    pip install mitsuba
    python tools/compare_multiple_scattering.py [--size 32] [--spp 1024] [--max-depth 64]
        [--abc 0.5,0.5,0.5 --abc 0.6,0.6,0.7,8] [--octaves 4] [--cache DIR]

The scene: a sphere of radius 1 (so σ_t·d = 2σ_t through its centre) with a homogeneous medium,
HG g = 0.8, one sun of irradiance 3 from the upper side (`testing/mitsuba.py`'s), no sky, the same
camera; Mitsuba's `volpath` with `max_depth` = `--max-depth` is the multiple-scattering reference
(max_depth = 2 is single scattering, which torchvol's plain physical shading must match). For each
(σ_t·d, albedo) it prints, against that reference: torchvol's single scattering, and single +
octaves for each `--abc` (a, b, c[, octaves], octaves defaulting to `--octaves`), as the mean ratio (torchvol mean / Mitsuba mean over the
image) and the relative RMSE; and Mitsuba's own single scattering against torchvol's (parity).
torchvol renders 16 stratified samples per pixel, as Mitsuba's box-filtered film averages pixels.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import torchvol as tv
from torchvol.measure.mitsuba import (
    EYE,
    FOV,
    IRRADIANCE,
    SUN,
    TARGET,
    relative_rmse,
    render_mitsuba_sphere,
)

CASES = [(5.0, 0.9), (10.0, 0.95), (20.0, 0.99)]  # (σ_t·d through the centre, albedo)
G = 0.8


def torchvol_scene(sigma_t: float, albedo: float, *, size: int, abc=None, octaves: int = 4) -> dict:
    volume = {"bounds": {"sphere": {"center": [0, 0, 0], "radius": 1.0}}, "density": {"constant": 1.0},
              "sigma_t": sigma_t, "albedo": albedo, "phase": {"hg": {"g": G}}}
    if abc is not None:
        volume["multiple_scattering"] = {"octaves": octaves, **dict(zip("abc", abc))}
    return {"image": {"width": size, "height": size, "spp": 16},
            "camera": {"eye": list(EYE), "target": list(TARGET), "fov_y": FOV},
            "lights": [{"direction": list(SUN), "intensity": IRRADIANCE, "shadow": {"steps": 32}}],
            "volumes": [volume], "march": {"quality": "high", "steps": 128}}


def mitsuba_image(sigma_t: float, albedo: float, *, size: int, spp: int, max_depth: int, cache: Path | None) -> np.ndarray:
    path = None if cache is None else cache / f"ms-{sigma_t}-{albedo}-{size}-{spp}-{max_depth}.npy"
    if path is not None and path.is_file():
        return np.load(path)
    image, _ = render_mitsuba_sphere(sigma_t, albedo, G, size=size, spp=spp, max_depth=max_depth)
    if path is not None:
        cache.mkdir(parents=True, exist_ok=True)
        np.save(path, image)
    return image


def row(label: str, image: np.ndarray, reference: np.ndarray) -> str:
    return f"| {label} | {image.mean() / reference.mean():.3f} | {relative_rmse(image, reference):.1%} |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=32)
    parser.add_argument("--spp", type=int, default=1024)
    parser.add_argument("--max-depth", type=int, default=64)
    parser.add_argument("--octaves", type=int, default=4)
    parser.add_argument("--abc", action="append", default=None, help="a,b,c[,octaves] (repeatable); default 0.5,0.5,0.5")
    parser.add_argument("--cache", type=Path, default=None, help="folder that keeps Mitsuba's renders between runs")
    args = parser.parse_args()
    settings = []
    for text in args.abc or ["0.5,0.5,0.5"]:
        values = [float(x) for x in text.split(",")]
        settings.append((tuple(values[:3]), int(values[3]) if len(values) > 3 else args.octaves))
    for depth_d, albedo in CASES:
        sigma_t = depth_d / 2.0
        start = time.perf_counter()
        multiple = mitsuba_image(sigma_t, albedo, size=args.size, spp=args.spp, max_depth=args.max_depth, cache=args.cache)
        single_ref = mitsuba_image(sigma_t, albedo, size=args.size, spp=args.spp, max_depth=2, cache=args.cache)
        print(f"\n## σ_t·d = {depth_d:g}, albedo {albedo}, HG g = {G}: against Mitsuba volpath max_depth {args.max_depth}, "
              f"{args.size}², {args.spp} spp ({time.perf_counter() - start:.0f} s)\n")
        print("| torchvol | mean / reference mean | relative RMSE |")
        print("| --- | ---: | ---: |")
        single = tv.render(torchvol_scene(sigma_t, albedo, size=args.size)).radiance[0].permute(1, 2, 0).numpy()
        print(row("single scattering", single, multiple))
        for abc, octaves in settings:
            img = tv.render(torchvol_scene(sigma_t, albedo, size=args.size, abc=abc, octaves=octaves))
            print(row(f"single + {octaves} octaves, a, b, c = {', '.join(f'{x:g}' for x in abc)}",
                      img.radiance[0].permute(1, 2, 0).numpy(), multiple))
        print(row("(parity) Mitsuba max_depth 2 vs torchvol single", single_ref, single), flush=True)


if __name__ == "__main__":
    main()
