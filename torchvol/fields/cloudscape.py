"""Production cloudscapes (seed 000, variant 4, Horizon Zero Dawn style): a cloud layer between
two altitudes, over flat ground or a planet, shaped by tileable Perlin-Worley and Worley noise:

    q = p − wind·time;  h = normalised height in the layer (0 at `bottom`, 1 at `top`)
    m = base(q / scale + offset) · gradient(h, type)            the cloud type's height profile
    m = m − erosion · 0.225 · detail(q / detail_scale + offset)  detail erosion
    density = smoothstep(0, 0.1, m + coverage − 1)               coverage remap

(the seeds' `cloudMapBase`, `cloudGradient`, `cloudMapDetail`, `COVERAGE`). Height is `p.y` over
flat ground, or the distance from the planet's centre (0, −planet_radius, 0) minus its radius: the
ground passes through the origin either way. The layer's bounds are the volume's: a slab from
`bottom` to `top` for flat ground, a `shell` for a planet.

The seeds' height-based ambient gradient (Step 6, Method C) is the volume's `ambient` with `top`
(`volume/ambient.py`), graded by altitude over a `shell`.
"""

from __future__ import annotations

from typing import Annotated

import torch
from pydantic import Field, model_validator
from torch import Tensor

from ..noise import tiles as noise_tiles
from ..ops.mathops import smoothstep
from ..schema.batch import Stacked, per_scene, take
from ..schema.models import EACH, Strict, Vec3

# Height profiles (smoothstep(a, b, h) · (1 − smoothstep(c, d, h)) over the normalised height h) of
# stratus, stratocumulus, cumulus, cumulonimbus: `type` 0, 1/3, 2/3, 1; between two, the profile's
# (a, b, c, d) blend linearly. a ≥ 0 and d ≤ 1: every profile is 0 at both ends of the layer.
CLOUD_TYPES = ((0.0, 0.1, 0.2, 0.3), (0.02, 0.2, 0.48, 0.625), (0.0, 0.15, 0.6, 0.85), (0.0, 0.06, 0.85, 1.0))
EROSION_SCALE = 0.225  # the seeds' `dstrength * 0.225`
COVERAGE_EDGE = 0.1  # the seeds' smoothstep(0.0, 0.1, ...)

class CloudscapeDensity(Strict):
    """A layer of production clouds between altitudes `bottom` and `top` (above the ground at y = 0;
    over a planet of `planet_radius` if given): Perlin-Worley shapes (period `scale`) under the
    height profile of cloud `type` (0 stratus, 1/3 stratocumulus, 2/3 cumulus, 1 cumulonimbus),
    eroded by Worley detail (period `detail_scale`), remapped by `coverage` (0: clear sky)."""

    seed: Annotated[int, EACH] = 0  # the noise textures (built once per seed: vary `offset` instead)
    bottom: float = 1.5
    top: float = 4.0
    planet_radius: float | None = Field(None, gt=0.0)
    type: float = Field(0.67, ge=0.0, le=1.0)
    coverage: float = Field(0.5, ge=0.0, le=1.0)
    erosion: float = Field(1.0, ge=0.0)
    scale: float = Field(16.0, gt=0.0)
    detail_scale: float = Field(2.0, gt=0.0)
    offset: Vec3 = (0.0, 0.0, 0.0)  # in texture periods: another sky from the same textures
    wind: Vec3 = (0.0, 0.0, 0.0)

    @model_validator(mode="after")
    def _layer(self):
        if self.top <= self.bottom:
            raise ValueError(f"top {self.top} must exceed bottom {self.bottom}")
        return self


def height_gradient(h: Tensor, cloud_type: Tensor) -> Tensor:
    """The cloud type's height profile. `h`: [n] normalised height (0 at the layer's bottom, 1 at
    its top; 0 outside [0, 1]); `cloud_type`: [n] in [0, 1]. -> [n] in [0, 1]."""
    table = torch.tensor(CLOUD_TYPES, dtype=h.dtype, device=h.device)  # [4, 4]
    x = cloud_type * (len(CLOUD_TYPES) - 1)
    lo = x.floor().clamp(0, len(CLOUD_TYPES) - 2).long()
    a, b, c, d = torch.lerp(table[lo], table[lo + 1], (x - lo)[:, None]).unbind(-1)
    return smoothstep(a, b, h) * (1.0 - smoothstep(c, d, h))


class Cloudscape:
    """The cloudscape densities of B scenes (per-scene tensors (B, ...), textures per seed)."""

    def __init__(self, params: Stacked, times: Tensor):
        self.p = params
        dtype = times.dtype
        self.textures = [(noise_tiles.base_texture(seed).to(dtype), noise_tiles.detail_texture(seed).to(dtype))
                         for seed in params.seed]
        self.shift = params.wind * times[:, None]  # (B, 3)
        # the detail texture's node spacing: finer than any shape the trilinear lookups can hold
        self.feature_size = torch.minimum(params.scale / noise_tiles.BASE_SIZE, params.detail_scale / noise_tiles.DETAIL_SIZE)

    def height(self, points: Tensor, scene_index: Tensor) -> Tensor:
        """Normalised height in the layer [n] of `points` [n, 3] (0 at bottom, 1 at top)."""
        p, s = self.p, scene_index
        if p.planet_radius is None:
            altitude = points[:, 1]
        else:
            radius = take(p.planet_radius, s)
            centre = torch.stack([torch.zeros_like(radius), -radius, torch.zeros_like(radius)], dim=1)
            altitude = (points - centre).norm(dim=1) - radius
        bottom = take(p.bottom, s)
        return (altitude - bottom) / (take(p.top, s) - bottom)

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        return self.signed(points, scene_index, lod).clamp_min(0.0)

    def signed(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        """The density where the coverage remap is positive, else the remap's argument (< 0)."""
        p, s = self.p, scene_index
        q = points - take(self.shift, s)
        offset = take(p.offset, s)
        base_uvw = q / take(p.scale, s)[:, None] + offset
        detail_uvw = q / take(p.detail_scale, s)[:, None] + offset

        def lookup(which: int, uvw: Tensor) -> Tensor:
            return per_scene(uvw, s, len(p), lambda b, _, x: noise_tiles.sample_tiled(self.textures[b][which], x))

        shape, erode = lookup(0, base_uvw), lookup(1, detail_uvw)
        m = shape * height_gradient(self.height(points, s), take(p.type, s))
        m = m - take(p.erosion, s) * EROSION_SCALE * erode
        x = (m + take(p.coverage, s) - 1.0) / COVERAGE_EDGE
        return torch.where(x > 0, smoothstep(0.0, 1.0, x), x)

