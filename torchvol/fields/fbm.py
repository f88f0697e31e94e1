"""An fbm noise cloud: density = max(bias + amplitude · fbm(frequency · (p − wind·time) + offset)
− radial · |p − center|, 0)."""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from .. import noise
from .base import per_scene

NOISES = {"value": noise.value_noise, "perlin": noise.perlin_noise, "worley": noise.worley_noise}


class FbmField:
    homogeneous = False

    def __init__(self, specs: Sequence, times: Tensor, *, compiled: bool = False):
        kw = dict(dtype=times.dtype, device=times.device)
        self.specs = list(specs)
        self.bases = {name: noise.compiled(fn) if compiled else fn for name, fn in NOISES.items()}
        self.frequency = torch.tensor([s.frequency for s in specs], **kw)
        self.amplitude = torch.tensor([s.amplitude for s in specs], **kw)
        self.bias = torch.tensor([s.bias for s in specs], **kw)
        self.offset = torch.tensor([s.offset for s in specs], **kw)
        self.shift = torch.tensor([s.wind for s in specs], **kw) * times[:, None]  # (B, 3)
        self.radial = torch.tensor([s.radial for s in specs], **kw)
        self.center = torch.tensor([s.center for s in specs], **kw)
        self.feature_size = torch.tensor([noise.finest_period(s.octaves) for s in specs], **kw) / self.frequency

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        return self.signed(points, scene_index, lod).clamp_min(0.0)

    def signed(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        q = self.frequency[scene_index, None] * (points - self.shift[scene_index]) + self.offset[scene_index]

        def one_scene(b: int, idx: Tensor | slice, q_b: Tensor) -> Tensor:
            spec = self.specs[b]
            basis = self.bases[spec.noise]
            return noise.fbm(q_b, lambda x: basis(x, seed=spec.seed), octaves=spec.octaves, lod=None if lod is None else lod[idx])

        f = per_scene(q, scene_index, len(self.specs), one_scene)
        falloff = self.radial[scene_index] * (points - self.center[scene_index]).norm(dim=1)
        return self.bias[scene_index] + self.amplitude[scene_index] * f - falloff
