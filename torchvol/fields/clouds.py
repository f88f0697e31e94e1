"""The seed template's cloud layer, `map(p, lod)`:

    q = p − wind·time;  f = fbm(q) of texture noise remapped to [−1, 1]
    density = clamp(bias − p.y + density_scale · f, 0, 1)     (the template: 1.5 − p.y − 2.0 + 1.75 f)
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Annotated, Any

import numpy as np
import torch
from pydantic import Field, field_validator
from torch import Tensor

from ..noise import lattice as noise
from ..ops import lanes
from ..schema.batch import Stacked, take
from ..schema.models import EACH, Strict, Vec3


class CloudsDensity(Strict):
    """The seed template's cloud layer `map()`:
    clamp(bias − p.y + density_scale · fbm(p − wind·time), 0, 1), fbm of texture noise in [−1, 1]."""

    texture_seed: Annotated[int, EACH] = 0
    texture: Annotated[Any, EACH] = None  # a PNG path or a uint8 array (256, 256, 4) [y, x, channel]
    octaves: int = Field(5, ge=1, le=5)
    density_scale: float = 1.75
    bias: float = -0.5
    wind: Vec3 = (0.0, 0.1, 1.0)

    @field_validator("texture")
    @classmethod
    def _texture(cls, v):
        if v is None:
            return None
        if isinstance(v, (str, Path)):
            if not Path(v).is_file():
                raise ValueError(f"no such file: {v}")
            from PIL import Image as PILImage

            v = np.asarray(PILImage.open(v).convert("RGBA"))
        array = np.asarray(v)
        if array.shape != (256, 256, 4) or array.dtype != np.uint8:
            raise ValueError(f"noise texture must be uint8 (256, 256, 4), got {array.dtype} {array.shape}")
        return array


class CloudLayer:
    def __init__(self, params: Stacked, times: Tensor):
        self.p = params
        tables = [
            noise.texture_table(torch.as_tensor(tex) if tex is not None else noise.default_noise_texture(seed), times.device)
            for tex, seed in zip(params.texture, params.texture_seed)
        ]
        # the integer filter's stacked tables (bitwise texture_noise_table, ~4× faster eager): one
        # pass over every scene's points, each at its scene's rows (`noise.texture_rows`); the
        # Dr.Jit march reads them too (`clouds_lanes`)
        self.packed = noise.packed_table(torch.cat(tables))
        self.shift = params.wind * times[:, None]  # (B, 3)
        self.feature_size = torch.full_like(times, noise.finest_period(params.octaves))

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        return self.signed(points, scene_index, lod).clamp_min(0.0)

    def signed(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        """The cloud layer's density before its clamp at 0 (negative: how far from having any):
        points [n, 3], scene_index [n], lod [n] octaves dropped or None -> [n]."""
        p, s = self.p, scene_index
        q = points - take(self.shift, s)
        octaves = None if lod is None else p.octaves - lod
        f = noise.fbm(q, lambda x, r: noise.texture_noise_coords(*x.unbind(1), self.packed, r) * 2.0 - 1.0,
                      octaves=p.octaves, lod=octaves, rows=noise.texture_rows(s, points.dtype))
        return cloud_density(f, points[:, 1], take(p.bias, s), take(p.density_scale, s))


def cloud_density(f, y, bias, density_scale):
    """The cloud layer's signed density bias − y + density_scale · f, at most 1, from its fbm `f`
    at height `y`; lanes (`ops.lanes`)."""
    return lanes.clamp_max(bias - y + density_scale * f, 1.0)


def cloud_fbm(x, y, z, packed, base, count, *, octaves: int, scales: list):
    """`noise.fbm` of the template's texture noise (`CloudLayer`) at points given as coordinates
    `x`, `y`, `z` [N], with its LOD as a mask: octave k ≥ 1 adds where `count` [N] (octaves kept)
    ≥ k + 1 (None: all), bitwise `noise.fbm`'s compaction. `base` [N]: the points' rows in the
    stacked `packed` tables. Lanes (`ops.lanes`): what the Dr.Jit march traces (`clouds_density`). -> [N]."""
    f = (noise.texture_noise_coords(x, y, z, packed, base) * 2.0 - 1.0) * 0.5
    for k in range(1, octaves):
        c = scales[k - 1]
        term = (noise.texture_noise_coords(x * c, y * c, z * c, packed, base) * 2.0 - 1.0) * (0.5 * 0.5**k)
        f = f + term if count is None else lanes.where(count >= k + 1, f + term, f)
    return f


def clouds_lanes(field: CloudLayer, to) -> SimpleNamespace:
    """What the cloud layer takes per lane (`to`: `fields.DENSITIES`' ``lanes`` inputs): its
    shift, bias and scale per lane, its stacked texture tables (`CloudLayer.packed`, int32) with
    each lane's first row in them, its octave count and scales (the kernel's parameters)."""
    p = field.p
    q = SimpleNamespace(shift=to.per_lane(field.shift), bias=to.per_lane(p.bias), density_scale=to.per_lane(p.density_scale),
                        packed=to.ints(field.packed), base=to.ints(noise.texture_rows(to.scene, torch.float32)),
                        octaves=int(p.octaves))
    q.scales = [to.number(c) for c in noise.folded_scales(q.octaves, dtype=torch.float32, device="cpu")]
    return q


def clouds_density(q: SimpleNamespace, p, count):
    """The cloud layer's signed density in lanes (`ops.lanes`) at p (three lanes), `count` octaves
    kept per lane or None; `q` from `clouds_lanes`."""
    f = cloud_fbm(p[0] - q.shift[0], p[1] - q.shift[1], p[2] - q.shift[2], q.packed, q.base, count,
                  octaves=q.octaves, scales=q.scales)
    return cloud_density(f, p[1], q.bias, q.density_scale)
