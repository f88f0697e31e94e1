"""Media shadings: the `SHADINGS` registry (`volumes[i].shading`). Each kind is its function
`fn(ctx, vol, rays, background, *, signed) -> Medium` (what the march samples) and capabilities:

- ``physical``: the medium is σ_t and a source (single scattering): it has closed forms, empty
  space skipping, error-controlled marching and shadowed lights;
- ``semantics``: the march's step semantics (`volume.march.march`): ``segments`` (exact
  segments, physical integrators) or ``shader`` (the seeds' loop and alpha compositing);
- ``lights``: which of the scene's lights shade it: ``all``, ``first`` (the seeds' derivative
  light) or ``unshadowed`` (all, their `shadow` settings not applying).
"""

from __future__ import annotations

from ..schema.registry import Registry
from .physical import physical_medium
from .shader_look import shader_medium
from .surface_look import surface_medium

SHADINGS = Registry("shading")
SHADINGS.register("physical", None, physical_medium, physical=True, semantics="segments", lights="all")
SHADINGS.register("shader", None, shader_medium, physical=False, semantics="shader", lights="first")
SHADINGS.register("surface", None, surface_medium, physical=False, semantics="shader", lights="unshadowed")
