"""Density fields: callables `field(points [N,3], scene_index [N], lod [N] | None) -> density [N]`.

Each field holds per-scene parameter tensors of shape (B, ...) and calls plain noise / sampling
functions, so B scenes of one structure evaluate in one call. `homogeneous` marks fields whose
density is constant in space (the planner may integrate those in closed form).
"""

from __future__ import annotations

from typing import Sequence

import torch

from .base import Field, per_scene
from .clouds import CloudLayer
from .constant import Constant
from .exponential import Exponential
from .fbm import FbmField
from .grid import Grid

__all__ = ["Field", "per_scene", "make_field", "Constant", "Exponential", "Grid", "FbmField", "CloudLayer"]


def make_field(specs: Sequence, bounds: Sequence, times: torch.Tensor, *, compiled: bool = False) -> Field:
    """The field for one volume slot of B scenes. `specs`: B `Density` models of one kind;
    `bounds`: their B `Bounds`; `times`: (B,) scene times (for wind); `compiled`: noise kernels
    under torch.compile."""
    kind = specs[0].kind
    values = [s.value for s in specs]
    if kind == "constant":
        return Constant(torch.tensor(values, dtype=times.dtype, device=times.device))
    if kind == "grid":
        return Grid([v.data for v in values], [b.box for b in bounds], dtype=times.dtype, device=times.device)
    if kind == "exponential":
        return Exponential(values, dtype=times.dtype, device=times.device)
    if kind == "fbm":
        return FbmField(values, times, compiled=compiled)
    if kind == "clouds":
        return CloudLayer(values, times, compiled=compiled)
    raise NotImplementedError(kind)
