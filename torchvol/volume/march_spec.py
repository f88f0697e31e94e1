"""What the template's fused march is specialised on, below both of its backends (the
torch.compile kernels of `volume.fused` and the Dr.Jit kernel of `volume.drjit_march`): the
per-scene values of the cloud layer's look and the constants of a compiled step."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

from torch import Tensor

from .march import StepRule


class CloudLook(NamedTuple):
    """Per-scene values of the cloud layer and its look, each (B, ...) in the render's dtype.

    `base` (B,) int32 for float32 (int64 for float64): the scene's first row in the stacked
    texture tables, of the texture noise's integer type (an int64 base would turn every index
    sum of the noise int64: 20% of the kernel's time)."""

    shift: Tensor  # (B, 3) wind · time
    bias: Tensor  # (B,)
    density_scale: Tensor  # (B,)
    light_step: Tensor  # (B, 3) light_offset · direction to the first light (zeros: no light)
    irradiance: Tensor  # (B, 3)
    light_scale: Tensor  # (B,)
    ambient: Tensor  # (B, 3)
    ambient_top: Tensor  # (B, 3) (= ambient: no height gradient)
    heights: Tensor  # (B, 2) the bounds' height range
    color_lit: Tensor  # (B, 3)
    color_dark: Tensor  # (B, 3)
    alpha_scale: Tensor  # (B,)
    fog: Tensor  # (B,)
    base: Tensor  # (B,)



@dataclass(frozen=True)
class StepConfig:
    """What a compiled step is specialised on (constants of its graph)."""

    rule: StepRule
    octaves: int
    lod_scale: float | None
    threshold: float
    min_transmittance: float
    max_iterations: int
    light: bool  # the derivative light is on
    graded: bool  # the ambient has a height gradient
