"""The Wrenninge octaves' (a, b, c) that fit every order of scattering best, per optical depth and albedo.

    python tools/fit_octaves.py [--size 32] [--paths 1024] [--passes 3]

A homogeneous sphere of radius 1 (σ_t·d through its centre as in `compare_multiple_scattering.py`),
HG g = 0.8, one sun, no sky. The reference is torchvol's `[path]` with every order of scattering
(bounces 1024; `--passes` independent renders of `--paths` paths a pixel, 4 stratified
sub-samples). Each candidate (a = b, c, octaves), a march (quality high, 16 stratified sub-samples),
is scored by its relative RMSE against the converged reference (`debiased_relative_rmse`: the
reference's noise subtracted) and its mean ratio; the table gives plain single scattering, the
schema's default (4 octaves, 0.5/0.5/0.5), the bundled presets' (6 octaves, 0.6/0.6/0.7) and the
best of the grid for each case.
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np

import torchvol as tv
from torchvol.measure.mitsuba import debiased_relative_rmse

sys.path.insert(0, str(Path(__file__).parent))
from compare_multiple_scattering import CASES, torchvol_scene  # noqa: E402

GRID_AB = tuple(round(0.15 + 0.05 * i, 2) for i in range(16))  # 0.15 … 0.9
GRID_C = tuple(round(0.1 * i, 1) for i in range(10))  # 0 (isotropic octaves) … 0.9
GRID_OCTAVES = (4, 8, 12)


def image(scene: dict, seed: int = 0) -> np.ndarray:
    return tv.render(scene, seed=seed).radiance[0].permute(1, 2, 0).double().numpy()


def reference(sigma_t: float, albedo: float, *, size: int, paths: int, passes: int) -> np.ndarray:
    scene = torchvol_scene(sigma_t, albedo, size=size)
    scene["image"]["spp"] = 4
    scene["path"] = {"bounces": 1024, "samples": max(1, paths // 4)}
    return np.stack([image(scene, seed=k) for k in range(passes)])


def score(candidate: np.ndarray, passes: np.ndarray) -> tuple[float, float]:
    return debiased_relative_rmse(candidate, passes)["rmse"], float(candidate.mean() / passes.mean())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=32)
    parser.add_argument("--paths", type=int, default=1024)
    parser.add_argument("--passes", type=int, default=3)
    args = parser.parse_args()
    print("| σ_t·d, albedo | single scattering | 4 octaves, 0.5/0.5/0.5 | 6 octaves, 0.6/0.6/0.7 | best of the grid |")
    print("| --- | ---: | ---: | ---: | --- |")
    for depth, albedo in CASES:
        sigma_t = depth / 2.0
        passes = reference(sigma_t, albedo, size=args.size, paths=args.paths, passes=args.passes)
        cells = []
        for abc, octaves in ((None, 0), ((0.5, 0.5, 0.5), 4), ((0.6, 0.6, 0.7), 6)):
            rmse, ratio = score(image(torchvol_scene(sigma_t, albedo, size=args.size, abc=abc, octaves=octaves)), passes)
            cells.append(f"{ratio:.3f}, {rmse:.0%}")
        best = None
        for ab, c, octaves in itertools.product(GRID_AB, GRID_C, GRID_OCTAVES):
            rmse, ratio = score(image(torchvol_scene(sigma_t, albedo, size=args.size, abc=(ab, ab, c), octaves=octaves)),
                                passes)
            if best is None or rmse < best[0]:
                best = (rmse, ratio, ab, c, octaves)
        rmse, ratio, ab, c, octaves = best
        print(f"| {depth:g}, {albedo} | {' | '.join(cells)} | {octaves} octaves, a = b = {ab:g}, c = {c:g}: "
              f"{ratio:.3f}, {rmse:.0%} |", flush=True)


if __name__ == "__main__":
    main()
