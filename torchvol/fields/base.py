"""The protocol every density field follows."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Protocol

from torch import Tensor

from ..ops import lanes
from ..schema.batch import take

# the largest density a render reads from any field (`renderer/stats.CountedField` caps every
# evaluation): 1e12 × `sigma_t` (≤ 1e12) is opaque over any step and still finite in float32, as is
# every optical depth summed from it; above ~1e26 the extinction overflows float32 to inf (and
# inf × 0 is NaN). A constant, a grid's values, an fbm's amplitude or a fur's scale may ask for more.
DENSITY_MAX = 1e12


class Field(Protocol):
    """A density field of B scenes, built by its kind from the batch's `Stacked` parameters
    (`Kind.fn(params, times)`, `times` (B,) for wind)."""

    # (B,) world length below which the density has no detail of its own (a grid's cell, an fbm's
    # finest octave), or None where there is none to resolve: error-controlled marching never
    # steps over half of it, since its estimate cannot see features that fall between samples
    feature_size: Tensor | None

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        """`points`: [N, 3]; `scene_index`: [N] long; `lod`: [N] octaves to drop (march.lod) or
        None. -> density [N] (≥ 0)."""
        ...

    def signed(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        """The density before its clamp at 0, same arguments -> [N]: negative where the field is
        empty, by how far it is from having density there (the density itself for a field never
        clamped). Smooth where the density has kinks, so error-controlled marching can interpolate
        it to find density between samples that all read 0."""
        ...


def torch_inputs(scene_index: Tensor) -> SimpleNamespace:
    """What a density kind's lanes inputs take (`DENSITIES`' ``lanes``) to run eagerly on torch
    columns for points of scenes `scene_index` [n]: per scene (B,) or (B, C) -> its lanes
    (`per_lane`), tables as they are (`floats`, `ints`)."""
    return SimpleNamespace(per_lane=lambda v: lanes.columns(take(v, scene_index)), scene=scene_index,
                           floats=lambda t: t, ints=lambda t: t)
