"""What the multiple-scattering approximations cost, against path-traced references, with the time.

    python tools/path_error.py [--preset cloud-puff] [--size 64] [--reference-paths 2048] [--passes 4]

The preset's march as it is (single scattering, its sky light and Wrenninge octaves), without its
octaves, and as plain single scattering, and `[path]` at several paths a pixel (every order
path-traced, and `single = "march"`: the march's single scattering plus the paths' other orders), each against the
preset path-traced with every order of scattering (bounces 256): the reference is the mean of
`--passes` independent renders of `--reference-paths` paths a pixel, and each error is the
relative RMSE against the converged render with the reference's own noise subtracted
(`debiased_relative_rmse`). Times are warm medians of three renders on this machine.
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time

import numpy as np
import torch

import torchvol as tv
from torchvol.measure.mitsuba import debiased_relative_rmse


def timed(scene: dict, seed: int = 0) -> tuple[np.ndarray, float]:
    tv.render(scene, seed=seed)  # kernels built, caches warm
    times, out = [], None
    for _ in range(3):
        start = time.perf_counter()
        out = tv.render(scene, seed=seed)
        times.append(time.perf_counter() - start)
    return out.radiance[0].permute(1, 2, 0).double().numpy(), statistics.median(times)


def variants(scene: dict) -> dict[str, dict]:
    """The march as the preset has it, without its octaves, and plain single scattering."""
    out = {"the preset's march (octaves, sky light)": scene}
    no_octaves = copy.deepcopy(scene)
    for v in no_octaves["volumes"]:
        v["multiple_scattering"] = None
    out["without its octaves (single scattering, sky light)"] = no_octaves
    single = copy.deepcopy(no_octaves)
    for v in single["volumes"]:
        v["ambient"] = None
        v["bloom"] = None
    out["plain single scattering"] = single
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="cloud-puff")
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--reference-paths", type=int, default=2048)
    parser.add_argument("--passes", type=int, default=4)
    args = parser.parse_args()
    scene = tv.preset(args.preset, width=args.size, height=args.size).model_dump()
    start = time.perf_counter()
    passes = np.stack([tv.render({**scene, "path": {"bounces": 256, "samples": args.reference_paths, "single": "paths"}}, seed=100 + k)
                       .radiance[0].permute(1, 2, 0).double().numpy() for k in range(args.passes)])
    print(f"{args.preset} at {args.size}²: reference = {args.passes} × {args.reference_paths} paths a pixel, "
          f"{time.perf_counter() - start:.0f} s; torch threads {torch.get_num_threads()}\n")
    print("| render | time s | relative RMSE against every order | mean / reference |")
    print("| --- | ---: | ---: | ---: |")
    reference_mean = passes.mean()
    rows = [(name, variant) for name, variant in variants(scene).items()]
    rows += [(f"`[path]`, {n} paths a pixel{' on the march' if single == 'march' else ''}",
              {**scene, "path": {"bounces": 256, "samples": n, "single": single}})
             for single in ("paths", "march") for n in (4, 16, 64, 256)]
    for name, variant in rows:
        image, seconds = timed(variant)
        err = debiased_relative_rmse(image, passes)
        print(f"| {name} | {seconds:.3f} | {err['rmse']:.1%} (±{(err['high'] - err['low']) / 2:.1%}) | "
              f"{image.mean() / reference_mean:.3f} |", flush=True)
    noise = debiased_relative_rmse(passes[0], passes[1:])
    print(f"\nthe reference's own noise (its mean of {args.passes} passes): {noise['noise']:.2%} of its RMS value")


if __name__ == "__main__":
    main()
