"""An exponential height profile: density = value · e^{−(y − base)/scale_height}, as in the seeds'
atmosphere (there radially; here along y)."""

from __future__ import annotations

import torch
from pydantic import Field
from torch import Tensor

from ..schema.batch import Stacked, take
from ..schema.models import Strict


class ExponentialDensity(Strict):
    """density = value · e^{−(y − base)/scale_height}."""

    value: float = Field(1.0, ge=0.0)
    base: float = 0.0
    scale_height: float = Field(1.0, gt=0.0)


class Exponential:
    feature_size = None  # smooth: the step-doubling estimate sees its curvature

    def __init__(self, params: Stacked, times: Tensor, *, compiled: bool = False):
        self.p = params

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        p, s = self.p, scene_index
        h = (points[:, 1] - take(p.base, s)) / take(p.scale_height, s)
        return take(p.value, s) * torch.exp(-h)

    signed = __call__  # never clamped: the density is its own signed value
