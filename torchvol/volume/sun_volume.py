"""Transmittance to a sun, precomputed once per scene on a sun-aligned grid.

A shadow march per sample costs K density evaluations per lit sample. For a directional light the
transmittance field T(p) = exp(−∫ σ_t(p + s·L) ds) can instead be tabulated once: resample the
extinction on a grid whose third axis runs along the sun direction L, accumulate the optical depth
towards the sun with a reverse cumulative sum (trapezoid rule per cell), exponentiate, and look T up
trilinearly wherever it is needed. Cost: one density evaluation per grid point, independent of the
image size and of the number of samples.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
import torch.nn.functional as F
from torch import Tensor


@dataclass(frozen=True)
class SunGrid:
    """Optical depth to the sun on a grid: `optical_depth` (Nw, Nv, Nu) over the frame `origin` +
    a·u + b·v + c·w with (a, b, c) in [0, size]; `frame` (3, 3) rows u, v, w (w towards the sun).
    Lookups interpolate the optical depth (smooth, near-linear along w) and exponentiate after:
    interpolating e^{−τ} itself is less accurate where τ changes fast."""

    optical_depth: Tensor
    origin: Tensor
    frame: Tensor
    size: Tensor

    def lookup(self, points: Tensor) -> Tensor:
        """Trilinear T at `points` [N, 3] (clamped to the grid's edge) -> [N]."""
        local = (points - self.origin) @ self.frame.T / self.size  # [N, 3] in [0, 1] inside
        # grid nodes sit at 0, 1/(n−1), ..., 1: align_corners=True addresses exactly those
        coords = (2.0 * local - 1.0).reshape(1, 1, 1, -1, 3)
        tau = F.grid_sample(self.optical_depth[None, None], coords, mode="bilinear", padding_mode="border", align_corners=True)
        return torch.exp(-tau.reshape(-1))


def sun_frame(sun_dir: Tensor) -> Tensor:
    """Rows (u, v, w): w = the unit sun direction, u and v completing a right-handed basis. [3] -> (3, 3)."""
    w = sun_dir / sun_dir.norm()
    helper = torch.tensor([0.0, 1.0, 0.0], dtype=w.dtype, device=w.device)
    if abs(float(w[1])) > 0.9:
        helper = torch.tensor([1.0, 0.0, 0.0], dtype=w.dtype, device=w.device)
    u = torch.linalg.cross(helper, w)
    u = u / u.norm()
    v = torch.linalg.cross(w, u)
    return torch.stack([u, v, w])


def sun_transmittance_grid(
    extinction: Callable[[Tensor], Tensor],
    box_min: Tensor,
    box_max: Tensor,
    sun_dir: Tensor,
    *,
    resolution: int,
) -> SunGrid:
    """Tabulate T to the sun over the box [box_min, box_max] (each [3]).

    `extinction(points [M, 3]) -> σ_t [M]` (0 outside the medium); `resolution` grid nodes along
    each axis of the sun-aligned frame that encloses the box. Nodes at the sun-side face have
    T = 1 (nothing lies beyond the box towards the sun)."""
    frame = sun_frame(sun_dir)
    corners = torch.stack(torch.meshgrid(*[torch.stack([box_min[i], box_max[i]]) for i in range(3)], indexing="ij"), -1)
    local = corners.reshape(-1, 3) @ frame.T  # corners in (u, v, w)
    lo, hi = local.min(dim=0).values, local.max(dim=0).values
    size = (hi - lo).clamp_min(torch.finfo(lo.dtype).tiny)
    origin = lo @ frame  # back to world
    n = resolution
    t = torch.linspace(0.0, 1.0, n, dtype=box_min.dtype, device=box_min.device)
    c, b, a = torch.meshgrid(t, t, t, indexing="ij")  # (Nw, Nv, Nu): w slowest
    abc = torch.stack([a, b, c], -1).reshape(-1, 3) * size
    points = origin + abc @ frame
    sigma = extinction(points).reshape(n, n, n)
    dw = size[2] / (n - 1)
    # optical depth from node k to the sun-side face: trapezoid sums of cells k..n−2, reversed
    cells = 0.5 * (sigma[1:] + sigma[:-1]) * dw  # (n−1, n, n)
    tau = torch.flip(torch.cumsum(torch.flip(cells, [0]), 0), [0])
    tau = torch.cat([tau, torch.zeros_like(sigma[:1])], dim=0)
    return SunGrid(optical_depth=tau, origin=origin, frame=frame, size=size)
