"""The seed template's cloud layer, `map(p, lod)`:

    q = p − wind·time;  f = fbm(q) of texture noise remapped to [−1, 1]
    density = clamp(bias − p.y + density_scale · f, 0, 1)     (the template: 1.5 − p.y − 2.0 + 1.75 f)
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from .. import noise
from .base import per_scene


class CloudLayer:
    homogeneous = False

    def __init__(self, specs: Sequence, times: Tensor, *, compiled: bool = False):
        kw = dict(dtype=times.dtype, device=times.device)
        self.specs = list(specs)
        self.tables = [
            noise.texture_table(
                torch.as_tensor(s.texture) if s.texture is not None else noise.default_noise_texture(s.texture_seed),
                times.device,
            )
            for s in specs
        ]
        self.kernel = noise.compiled(noise.texture_noise_table) if compiled else noise.texture_noise_table
        self.shift = torch.tensor([s.wind for s in specs], **kw) * times[:, None]  # (B, 3)
        self.scale = torch.tensor([s.density_scale for s in specs], **kw)
        self.bias = torch.tensor([s.bias for s in specs], **kw)
        self.feature_size = torch.tensor([noise.finest_period(s.octaves) for s in specs], **kw)

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        return self.signed(points, scene_index, lod).clamp_min(0.0)

    def signed(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        q = points - self.shift[scene_index]

        def one_scene(b: int, idx: Tensor | slice, q_b: Tensor) -> Tensor:
            table = self.tables[b]
            return noise.fbm(
                q_b, lambda x: self.kernel(x, table) * 2.0 - 1.0,
                octaves=self.specs[b].octaves, lod=None if lod is None else lod[idx],
            )

        f = per_scene(q, scene_index, len(self.specs), one_scene)
        return (self.bias[scene_index] - points[:, 1] + self.scale[scene_index] * f).clamp_max(1.0)
