"""The protocol every density field follows, and the per-scene grouping helper."""

from __future__ import annotations

from typing import Callable, Protocol

from torch import Tensor


class Field(Protocol):
    homogeneous: bool
    # (B,) world length below which the density has no detail of its own (a grid's cell, an fbm's
    # finest octave), or None where there is none to resolve: error-controlled marching never
    # steps over half of it, since its estimate cannot see features that fall between samples
    feature_size: Tensor | None

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        """`points`: [N, 3]; `scene_index`: [N] long; `lod`: [N] octave counts or None. -> [N]."""
        ...

    def signed(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        """The density before its clamp at 0, same arguments -> [N]: negative where the field is
        empty, by how far it is from having density there (the density itself for a field never
        clamped). Smooth where the density has kinks, so error-controlled marching can interpolate
        it to find density between samples that all read 0."""
        ...


def per_scene(
    points: Tensor, scene_index: Tensor, batch: int, fn: Callable[[int, Tensor | slice, Tensor], Tensor]
) -> Tensor:
    """Evaluate `fn(b, index, points_b) -> [n_b]` on the points of each scene b, for fields whose
    per-scene state (a seed, a texture, a grid) cannot be gathered per point. `index` selects scene
    b's points from per-point tensors: an index tensor, or `slice(None)` when there is one scene."""
    if batch == 1:
        return fn(0, slice(None), points)
    out = points.new_zeros(points.shape[0])
    for b in range(batch):
        idx = (scene_index == b).nonzero().squeeze(1)
        if idx.numel():
            out[idx] = fn(b, idx, points[idx])
    return out
