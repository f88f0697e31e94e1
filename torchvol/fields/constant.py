"""A homogeneous medium: one density per scene."""

from __future__ import annotations

from torch import Tensor


class Constant:
    homogeneous = True
    feature_size = None

    def __init__(self, value: Tensor):  # (B,)
        self.value = value

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        return self.value[scene_index]

    signed = __call__  # never clamped: the density is its own signed value
