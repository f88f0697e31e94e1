"""Production cloudscapes (seed 000, variant 4, Horizon Zero Dawn style): a cloud layer between
two altitudes, over flat ground or a planet, shaped by tileable Perlin-Worley and Worley noise:

    q = p − wind·time;  h = normalised height in the layer (0 at `bottom`, 1 at `top`)
    m = base(q / scale + offset) · gradient(h, type)            the cloud type's height profile
    m = m − erosion · 0.225 · detail(q / detail_scale + offset)  detail erosion
    density = smoothstep(0, 0.1, m + coverage − 1)               coverage remap

(the seeds' `cloudMapBase`, `cloudGradient`, `cloudMapDetail`, `COVERAGE`). Height is `p.y` over
flat ground, or the distance from the planet's centre (0, −planet_radius, 0) minus its radius
(`geometry.bounds.shell_altitude`): the ground passes through the origin either way. Written once
in lanes (`cloudscape_density`): the eager field runs it on torch columns, the Dr.Jit march traces
it (`fields.DENSITIES`' ``lanes``). The layer's bounds are the volume's: a slab from
`bottom` to `top` for flat ground, a `shell` for a planet.

The seeds' height-based ambient gradient (Step 6, Method C) is the volume's `ambient` with `top`
(`volume/ambient.py`), graded by altitude over a `shell`.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Annotated

import torch
from pydantic import Field, model_validator
from torch import Tensor

from ..geometry.bounds import shell_altitude
from ..noise import tiles as noise_tiles
from ..ops import lanes
from ..schema.batch import Stacked, take
from ..schema.models import EACH, Strict, Vec3
from .base import torch_inputs

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


def height_gradient(h, cloud_type):
    """The cloud type's height profile, in lanes (`ops.lanes`). `h`: normalised height (0 at the
    layer's bottom, 1 at its top; 0 outside [0, 1]); `cloud_type` in [0, 1]. -> lanes in [0, 1]."""
    x = cloud_type * (len(CLOUD_TYPES) - 1)
    lo = lanes.clamp(lanes.floor(x), 0, len(CLOUD_TYPES) - 2)
    w = x - lo

    def row(i: int, k: int):  # column k of the table's row lo + i
        rows = CLOUD_TYPES[i:i + len(CLOUD_TYPES) - 1]
        out = lanes.full_like(x, rows[-1][k])
        for j in reversed(range(len(rows) - 1)):
            out = lanes.where(lo == j, rows[j][k], out)
        return out

    a, b, c, d = (lanes.lerp(row(0, k), row(1, k), w) for k in range(4))
    return lanes.smoothstep01((h - a) / (b - a)) * (1.0 - lanes.smoothstep01((h - c) / (d - c)))


def layer_height(q: SimpleNamespace, p):
    """Normalised height in the layer of `p` (three lanes; 0 at bottom, 1 at top): `p.y` over flat
    ground, the altitude above the planet of radius `q.planet_radius` (None: flat) otherwise;
    lanes (`ops.lanes`), `q` from `cloudscape_lanes`."""
    altitude = p[1] if q.planet_radius is None else shell_altitude(p, q.planet_radius)
    return (altitude - q.bottom) / (q.top - q.bottom)


def cloudscape_density(q: SimpleNamespace, p, count=None):
    """The signed density at `p` (three lanes): where the coverage remap is positive the density,
    else the remap's argument (< 0); lanes (`ops.lanes`), `q` from `cloudscape_lanes` (`count`,
    the octaves kept, does not apply: the textures hold every octave)."""
    moved = [p[c] - q.shift[c] for c in range(3)]  # the point the wind brought here
    shape = noise_tiles.tiled_lanes(q.base, noise_tiles.BASE_SIZE, q.base_row,
                                    *(moved[c] / q.scale + q.offset[c] for c in range(3)))
    erode = noise_tiles.tiled_lanes(q.detail, noise_tiles.DETAIL_SIZE, q.detail_row,
                                    *(moved[c] / q.detail_scale + q.offset[c] for c in range(3)))
    m = shape * height_gradient(layer_height(q, p), q.type)
    m = m - q.erosion * EROSION_SCALE * erode
    x = (m + q.coverage - 1.0) / COVERAGE_EDGE
    return lanes.where(x > 0, lanes.smoothstep01(x), x)


def cloudscape_lanes(field: Cloudscape, to) -> SimpleNamespace:
    """What the cloudscape takes per lane (`to`: as `fields.DENSITIES`' ``lanes`` inputs): its
    values, and the batch's textures as flat tables with each lane's first row in them."""
    p = field.p
    q = SimpleNamespace(**{k: to.per_lane(getattr(p, k)) for k in ("bottom", "top", "type", "coverage", "erosion",
                                                                    "scale", "detail_scale", "offset")})
    q.shift = to.per_lane(field.shift)
    q.planet_radius = None if p.planet_radius is None else to.per_lane(p.planet_radius)
    texture = take(field.texture, to.scene)  # each lane's place among the textures
    q.base, q.base_row = to.floats(field.base), to.ints(texture * noise_tiles.BASE_SIZE**3)
    q.detail, q.detail_row = to.floats(field.detail), to.ints(texture * noise_tiles.DETAIL_SIZE**3)
    return q


class Cloudscape:
    """The cloudscape densities of B scenes (per-scene tensors (B, ...), textures per seed: each
    distinct seed's base and detail textures flattened one after the other, `texture` (B,) a
    scene's place among them)."""

    def __init__(self, params: Stacked, times: Tensor):
        self.p = params
        seeds = list(dict.fromkeys(int(seed) for seed in params.seed))
        self.texture = torch.tensor([seeds.index(int(seed)) for seed in params.seed], dtype=torch.int32, device=times.device)
        # one seed: the cached texture itself, not a copy (8 MB: ~3 ms a render)
        join = lambda parts: parts[0] if len(parts) == 1 else torch.cat(parts)  # noqa: E731
        self.base = join([noise_tiles.base_texture(seed).reshape(-1) for seed in seeds]).to(times)
        self.detail = join([noise_tiles.detail_texture(seed).reshape(-1) for seed in seeds]).to(times)
        self.shift = params.wind * times[:, None]  # (B, 3)
        # the detail texture's node spacing: finer than any shape the trilinear lookups can hold
        self.feature_size = torch.minimum(params.scale / noise_tiles.BASE_SIZE, params.detail_scale / noise_tiles.DETAIL_SIZE)

    def _lanes(self, points: Tensor, scene_index: Tensor) -> SimpleNamespace:
        """`cloudscape_lanes` on torch columns, for `points` [n, 3] of scenes `scene_index` [n]."""
        return cloudscape_lanes(self, torch_inputs(scene_index))

    def height(self, points: Tensor, scene_index: Tensor) -> Tensor:
        """Normalised height in the layer [n] of `points` [n, 3] (0 at bottom, 1 at top)."""
        return layer_height(self._lanes(points, scene_index), points.unbind(1))

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        return self.signed(points, scene_index, lod).clamp_min(0.0)

    def signed(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        """The density where the coverage remap is positive, else the remap's argument (< 0):
        `cloudscape_density` on torch columns, `points` [n, 3] -> [n] (`lod` does not apply)."""
        return cloudscape_density(self._lanes(points, scene_index), points.unbind(1))
