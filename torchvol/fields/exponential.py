"""An exponential height profile: density = value · e^{−(y − base)/scale_height}, as in the seeds'
atmosphere (there radially; here along y)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import torch
from pydantic import Field
from torch import Tensor

from ..ops import lanes
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

    def __init__(self, params: Stacked, times: Tensor):
        self.p = params

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        p, s = self.p, scene_index
        q = SimpleNamespace(value=take(p.value, s), base=take(p.base, s), scale_height=take(p.scale_height, s))
        return exponential_density(q, points.unbind(1), None)

    signed = __call__  # never clamped: the density is its own signed value


# the closed-form depth's cap (`exponential_optical_depth`): e^{−σ_t·1e30} is 0 for any σ_t the
# schema allows above 1e-28, and the cap keeps a dense fog's depth finite (float32 overflowed to inf,
# and σ_t = 0 times inf is NaN)
DEPTH_MAX = 1e30

SLAB = 0.5  # a local majorants' slab's thickness in scale heights (`exponential_macro`)


def exponential_macro(field: Exponential, b: int, low: Tensor, high: Tensor, cells: int) -> tuple[Tensor, Tensor, Tensor]:
    """Scene b's profile's local majorants (`volume.local_majorant`): its box [low, high] ([3]
    each) in slabs `SLAB` scale heights thick (at most `cells` of them), each the whole box wide ->
    (bounds (1, H, 1): the density at each slab's lowest point, where it peaks; their corner [3],
    size [3])."""
    low, high = low.to(torch.float64), high.to(torch.float64)
    extent = high - low
    slabs = max(1, min(cells, math.ceil(float(extent[1]) / (SLAB * float(field.p.scale_height[b])))))
    thick = float(extent[1]) / slabs
    y = low[1] + thick * torch.arange(slabs, dtype=torch.float64)
    h = (y - float(field.p.base[b])) / float(field.p.scale_height[b])
    bound = (float(field.p.value[b]) * torch.exp((-h).clamp(max=LOG_DENSITY_MAX))).clamp(max=DENSITY_MAX)
    size = torch.stack([extent[0], torch.tensor(thick, dtype=torch.float64), extent[2]])
    return bound[None, :, None], low, size


def exponential_lanes(field: Exponential, to) -> SimpleNamespace:
    """What the profile takes per lane (`to.per_lane`: per scene -> lanes)."""
    return SimpleNamespace(value=to.per_lane(field.p.value), base=to.per_lane(field.p.base),
                           scale_height=to.per_lane(field.p.scale_height))


def exponential_optical_depth(q, start, direction, length):
    """∫ density ds over `length` (lanes) of a line leaving a point of density `start` along the
    unit `direction` (three lanes), in closed form: start · length · (1 − e^{−x})/x, x =
    d_y·length/H the exponent's fall over it (the factor 1 at x = 0); `q` from
    `exponential_lanes`. Exact where a shadow march or a sun grid approximates. A ray falling
    more than 80 scale heights saturates, and the depth stops at `DEPTH_MAX` (either already makes
    T 0): no inf, so σ_t = 0 still gives T = 1, never 0 × inf; start or length 0 gives 0."""
    x = lanes.clamp_min(direction[1] * length / q.scale_height, -80.0)
    fall = lanes.where(x == 0.0, 1.0, -lanes.expm1(-x) / lanes.where(x == 0.0, 1.0, x))
    return lanes.clamp_max(start * length * fall, DEPTH_MAX)


def exponential_density(q, p, count):
    """value · e^{−(y − base)/H} in lanes (`ops.lanes`) at p (three lanes), `q` from
    `exponential_lanes`: the exponent capped before exp (no inf, so value 0 gives 0), the product
    capped after."""
    h = (p[1] - q.base) / q.scale_height
    return lanes.clamp_max(q.value * lanes.exp(lanes.clamp_max(-h, LOG_DENSITY_MAX)), DENSITY_MAX)
