"""What the joint march of media that share space costs, and what its steps buy.

A cumulus (fbm, sky light, multiple-scattering octaves) standing in a hazy exponential fog, lit by
a shadowed sun, the two marched together (`media.march`). For `march.steps` in a ladder: the mean
absolute error of the radiance against a float64 render at 256 steps, and the median time of
three renders (one thread). Run on a quiet machine:

    python tools/bench_joint.py [--size 128]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

import torchvol as tv


def scene(size: int, steps: int) -> dict:
    """The cloud in fog at `size`² with `steps` steps per piece."""
    cloud = {"bounds": {"sphere": {"center": [0.0, 0.0, 0.0], "radius": 1.0}},
             "density": {"fbm": {"octaves": 4, "frequency": 2.2, "seed": 7, "bias": 0.9, "amplitude": 2.5,
                                 "radial": 2.8}},
             "sigma_t": 12.0, "albedo": 0.95, "phase": {"hg": {"g": 0.6}},
             "ambient": {"visibility": "march", "steps": 2, "sigma_scale": 0.25},
             "multiple_scattering": {"octaves": 4, "a": 0.6, "b": 0.6, "c": 0.7}}
    fog = {"bounds": {"box": {"min": [-4.0, -1.5, -4.0], "max": [4.0, 0.6, 4.0]}},
           "density": {"exponential": {"value": 1.0, "base": -1.5, "scale_height": 0.8}},
           "sigma_t": 0.6, "albedo": 0.9, "phase": {"hg": {"g": 0.3}}}
    return {"image": {"width": size, "height": size},
            "camera": {"eye": [0.0, 0.6, -3.4], "target": [0.0, -0.1, 0.0], "fov_y": 50.0},
            "sky": {"kind": "constant", "radiance": [0.3, 0.4, 0.6]},
            "lights": [{"kind": "sun", "direction": [0.5, 0.8, 0.3], "intensity": 8.0, "shadow": {"steps": 6}}],
            "volumes": [cloud, fog], "march": {"steps": steps}}


def main() -> None:
    """Prints one row per step count: steps, error, time, march steps."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=128)
    args = parser.parse_args()
    torch.set_num_threads(1)
    reference = tv.render(scene(args.size, 256), dtype=torch.float64).radiance
    print(f"reference: float64, 256 steps per piece, mean radiance {reference.mean():.4f}")
    print("steps  mean |error|  relative  time (s, median of 3)  march steps")
    for steps in (8, 16, 32, 64):
        times, out = [], None
        for _ in range(3):
            start = time.perf_counter()
            out = tv.render(scene(args.size, steps))
            times.append(time.perf_counter() - start)
        error = (out.radiance.double() - reference).abs().mean().item()
        print(f"{steps:5d}  {error:12.2e}  {error / reference.mean().item():8.2%}  {statistics.median(times):21.3f}"
              f"  {out.stats['march_steps']:11d}")


if __name__ == "__main__":
    main()
