"""An exponential height profile: density = value · e^{−(y − base)/scale_height}, as in the seeds'
atmosphere (there radially; here along y)."""

from __future__ import annotations

import math

import torch
from pydantic import Field
from torch import Tensor

from ..schema.batch import Stacked, take
from ..schema.models import Strict
from .base import DENSITY_MAX

# far below its base a small scale height overflows e^{(base − y)/H} (e^{1000} is inf, and inf × 0
# NaN): the field itself stops at DENSITY_MAX (fields/base.py), before the exponential overflows
LOG_DENSITY_MAX = math.log(DENSITY_MAX)


class ExponentialDensity(Strict):
    """density = value · e^{−(y − base)/scale_height}, at most 1e12 (`DENSITY_MAX`)."""

    value: float = Field(1.0, ge=0.0, le=DENSITY_MAX)
    base: float = 0.0
    scale_height: float = Field(1.0, gt=0.0)


class Exponential:
    feature_size = None  # smooth: the step-doubling estimate sees its curvature

    def __init__(self, params: Stacked, times: Tensor, *, compiled: bool = False):
        self.p = params

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        p, s = self.p, scene_index
        h = (points[:, 1] - take(p.base, s)) / take(p.scale_height, s)
        # the exponent capped before exp (no inf, so value 0 gives 0), the product capped after
        return (take(p.value, s) * torch.exp((-h).clamp_max(LOG_DENSITY_MAX))).clamp_max(DENSITY_MAX)

    signed = __call__  # never clamped: the density is its own signed value
