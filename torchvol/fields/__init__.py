"""Density fields: the `DENSITIES` registry. Each kind is its schema model (the table under
`density = { kind = ... }`), its field class (built per batch: `fn(params, times)`,
called as `field(points [N, 3], scene_index [N], lod [N] | None) -> density [N]`) and its
capabilities:

- ``homogeneous``: constant in space (a medium with a closed form along any ray);
- ``skippable``: the field knows where it is empty (`occupancy(b)`), so the march skips the rest;
- ``needs_box``: spans its volume's box (the box is handed to `fn` as ``box_min``, ``box_max``);
- ``cheap``: a sample costs less than compacting the march's batch (the march keeps finished rays
  in the batch longer);
- ``octaves``: a sum of octaves that `march.lod` may cut short with distance;
- ``lanes = (inputs, density)``: the density written once in lanes (`ops.lanes`), what the Dr.Jit
  march traces (`volume.kernel_march`; the template's cloud layer too, in the seeds' look):
  `inputs(field, to)` its per-lane parameters,
  `density(q, p, count)` its signed density at p (three lanes), `count` octaves kept or None;
  `supports(volume) -> bool` where a kind renders only some of its variants.

Each field holds per-scene parameter tensors of shape (B, ...) and calls plain noise / sampling
functions, so B scenes of one structure evaluate in one call.
"""

from __future__ import annotations

import torch

from ..schema.registry import Registry
from .base import Field
from .clouds import CloudLayer, CloudsDensity, clouds_density, clouds_lanes
from .cloudscape import (
                   Cloudscape,
                   CloudscapeDensity,
                   cloudscape_density,
                   cloudscape_lanes,
)
from .constant import (
                   Constant,
                   ConstantDensity,
                   constant_density,
                   constant_lanes,
                   constant_optical_depth,
)
from .explosion import (
                   ExplosionDensity,
                   ExplosionField,
                   explosion_density,
                   explosion_lanes,
)
from .exponential import (
                   Exponential,
                   ExponentialDensity,
                   exponential_density,
                   exponential_lanes,
                   exponential_macro,
                   exponential_optical_depth,
)
from .fbm import FbmDensity, FbmField, fbm_density, fbm_lanes, fbm_macro
from .fur import FurDensity, FurField, fur_density, fur_lanes
from .grid import Grid, GridDensity, grid_density, grid_lanes, grid_macro
from .particles import (
                   ParticleField,
                   ParticlesDensity,
                   particles_density,
                   particles_lanes,
)

DENSITIES = Registry("density")
DENSITIES.register("constant", ConstantDensity, Constant, homogeneous=True, lanes=(constant_lanes, constant_density),
                   optical_depth=constant_optical_depth)
DENSITIES.register("grid", GridDensity, Grid, skippable=True, needs_box=True, cheap=True, lanes=(grid_lanes, grid_density),
                   macro=grid_macro)
DENSITIES.register("exponential", ExponentialDensity, Exponential, lanes=(exponential_lanes, exponential_density),
                   macro=exponential_macro, optical_depth=exponential_optical_depth)
# `optical_depth(q, start, direction, length)`: ∫ density along a line in closed form, lanes over the
# kind's lanes inputs `q` from the density `start` where it leaves (every shadow and sky ray through
# such a volume takes it, `VolumePass.line_integral`: no march, no sun grid)
# `bound`: an upper bound (B,) of the density from its parameters (the path tracer's majorant):
# an fbm's basis noises lie in [−1, 1] and its octave weights sum under 1; a cloudscape's remap is a smoothstep.
# `macro(field, b, low, high, cells)`: scene b's bounds over macro cells of its box (`volume.local_majorant`), or None
DENSITIES.register("fbm", FbmDensity, FbmField, octaves=True, lanes=(fbm_lanes, fbm_density),
                   bound=lambda f: f.bias + f.amplitude.abs(), macro=fbm_macro)
DENSITIES.register("clouds", CloudsDensity, CloudLayer, octaves=True, lanes=(clouds_lanes, clouds_density))
DENSITIES.register("explosion", ExplosionDensity, ExplosionField, octaves=True, lanes=(explosion_lanes, explosion_density))
DENSITIES.register("cloudscape", CloudscapeDensity, Cloudscape, lanes=(cloudscape_lanes, cloudscape_density),
                   bound=lambda c: torch.ones_like(c.coverage))
DENSITIES.register("particles", ParticlesDensity, ParticleField, octaves=True, lanes=(particles_lanes, particles_density))
DENSITIES.register("fur", FurDensity, FurField, lanes=(fur_lanes, fur_density))

__all__ = ["DENSITIES", "Field"]
