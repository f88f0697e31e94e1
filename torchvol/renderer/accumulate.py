"""Progressive accumulation (`image.passes = N`): the offline form of the seeds' temporal
reprojection. The render runs its plan N times, each pass with its own march dither and sub-pixel
jitter (per-scene seeds hashed from (scene seed, pass index); pass 0 uses the scene's seed, so one
pass is the render without accumulation), and blends the passes' per-pixel outputs before post:

- ``mean`` (default): the running mean, the same as N times the samples per pixel (a key that
  resolves as ``hit_mean``, depth, averages over the passes that hit; ids keep pass 0's);
- ``exponential``: the seeds' history blend mix(old, new, `blend_weight`) after each pass, pass 0
  the initial history (ids keep pass 0's).

`Accumulator.changes` records the convergence: after each pass k ≥ 1, the mean |change| of the
blended radiance (the running mean's or the history's)."""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from ..noise import lattice as noise
from .aovs import RESOLVE


def pass_seeds(seeds: Tensor, k: int) -> Tensor:
    """Pass `k`'s per-scene seeds (B,) int64 from the scenes' `seeds` (B,): the seeds themselves for
    pass 0, a 32-bit hash of (seed, k) after."""
    if k == 0:
        return seeds
    cells = torch.stack([seeds, torch.full_like(seeds, k), torch.zeros_like(seeds)], dim=1)
    return (noise.hash3(cells, 0xACC, dtype=torch.float64) * 2.0**32).long()  # exact: the hash's 32 bits


class Accumulator:
    """Blends successive passes' per-pixel buffers {key: [C, P]} (P = B·H·W pixels, scene-major).
    `weight`: (B,) the exponential blend's weight per scene; `pixels_per_scene`: H·W."""

    def __init__(self, mode: Literal["mean", "exponential"], weight: Tensor, pixels_per_scene: int):
        self.mode, self.passes = mode, 0
        self.weight = weight.to(torch.float32).repeat_interleave(pixels_per_scene)  # [P]
        self.sums: dict[str, Tensor] = {}
        self.hits: dict[str, Tensor] = {}  # hit_mean keys (mean blend): passes that hit, [1, P]
        self.changes: list[float] = []

    def add(self, buffers: dict[str, Tensor]) -> None:
        """Blend in one pass's buffers."""
        before = self.value("radiance") if self.passes else None
        self.passes += 1
        for key, new in buffers.items():
            mode = RESOLVE[key]
            if key not in self.sums:
                self.sums[key] = new.clone()
                if mode == "hit_mean" and self.mode == "mean":
                    self.hits[key] = (new > 0).to(new.dtype)
            elif mode == "first":
                continue
            elif self.mode == "exponential":
                self.sums[key] = torch.lerp(self.sums[key], new, self.weight)
            else:
                self.sums[key] += new
                if key in self.hits:
                    self.hits[key] += new > 0
        if before is not None:
            self.changes.append(float((self.value("radiance") - before).abs().mean()))

    def value(self, key: str) -> Tensor:
        """The blend so far of `key` -> [C, P]."""
        total = self.sums[key]
        if self.mode == "exponential" or RESOLVE[key] == "first":
            return total
        if key in self.hits:
            return total / self.hits[key].clamp_min(1.0)
        return total / self.passes

    def result(self) -> dict[str, Tensor]:
        """Every accumulated key's blend so far: {key: [C, P]}."""
        return {key: self.value(key) for key in self.sums}


__all__ = ["Accumulator", "pass_seeds"]
