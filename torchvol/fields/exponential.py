"""An exponential height profile: density = value · e^{−(y − base)/scale_height}, as in the seeds'
atmosphere (there radially; here along y, so a slab of it has a closed-form optical depth)."""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from ..volume.integrate import one_minus_exp_over_x


class Exponential:
    homogeneous = False
    feature_size = None  # smooth: the step-doubling estimate sees its curvature

    def __init__(self, specs: Sequence, *, dtype, device):
        self.value = torch.tensor([s.value for s in specs], dtype=dtype, device=device)
        self.base = torch.tensor([s.base for s in specs], dtype=dtype, device=device)
        self.scale_height = torch.tensor([s.scale_height for s in specs], dtype=dtype, device=device)

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        h = (points[:, 1] - self.base[scene_index]) / self.scale_height[scene_index]
        return self.value[scene_index] * torch.exp(-h)

    signed = __call__  # never clamped: the density is its own signed value


def optical_depth(o_y: Tensor, d_y: Tensor, t0: Tensor, t1: Tensor, *, value: float, base: float, scale_height: float) -> Tensor:
    """∫_{t0}^{t1} value·e^{−(o_y + t d_y − base)/H} dt in closed form (d_y → 0 handled). All [R]."""
    h0 = (o_y + t0 * d_y - base) / scale_height
    k = d_y / scale_height * (t1 - t0)  # growth of h over the segment
    # ∫ = value·e^{−h0}·(t1 − t0)·(1 − e^{−k})/k; for k < 0 that is e^{|k|}·(1 − e^{−|k|})/|k|
    phi = one_minus_exp_over_x(k.abs())
    phi = torch.where(k >= 0, phi, torch.exp(k.abs()) * phi)
    return value * torch.exp(-h0) * (t1 - t0) * phi
