"""A homogeneous medium: one density per scene (`density = { constant = 1.0 }`)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Annotated

from pydantic import Field
from torch import Tensor

from ..schema.batch import take

ConstantDensity = Annotated[float, Field(ge=0.0)]


class Constant:
    feature_size = None

    def __init__(self, value: Tensor, times: Tensor):  # value (B,)
        self.value = value

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        return take(self.value, scene_index)

    signed = __call__  # never clamped: the density is its own signed value


def constant_lanes(field: Constant, to) -> SimpleNamespace:
    """What the constant takes per lane (`to.per_lane`: per scene -> lanes)."""
    return SimpleNamespace(value=to.per_lane(field.value))


def constant_optical_depth(q, start, direction, length):
    """∫ density along `length` (lanes) of a line leaving a point of density `start`: start · length,
    exactly (`q` and `direction` unread; `fields.DENSITIES`' ``optical_depth``)."""
    return start * length


def constant_density(q, p, count):
    """The constant's density in lanes (`ops.lanes`): `q` from `constant_lanes`."""
    return q.value
