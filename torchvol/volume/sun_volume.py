"""Transmittance to a sun, precomputed once per scene on a sun-aligned grid.

A shadow march per sample costs K density evaluations per lit sample. For a directional light the
optical depth τ(p) = ∫ σ_t(p + s·L) ds can instead be tabulated once: sample the extinction on
planes across the sun direction L (two sub-planes per stored plane), and accumulate τ towards the
sun with a reverse cumulative sum of Simpson's rule over each pair of sub-planes. Only the nodes
inside the medium's bounds are evaluated (`chord`). A lookup then needs
only what lies between the point and the next stored plane towards the sun:

    τ(p) = τ_plane(u, v) + ½·gap·(σ_t(p) + σ_plane(u, v)),

with τ_plane and σ_plane (σ_t where the sun ray from p meets that plane) interpolated bicubically
inside the plane: the planes are laid side by side in one 2-channel 2D atlas, so one `grid_sample`
call serves every point. Interpolating across L is what costs accuracy: bicubic planes are closer
to the exact transmittance than trilinear interpolation of the same table, and the gap term removes
the interpolation along L (docs/VOLUMES.md has the figures). Cost: one density evaluation per table
node; a lookup needs none.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace
from typing import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

from ..ops import lanes

PAD = 2  # replicated border around each plane in the atlas: bicubic taps reach 2 texels out
NODE_CHUNK = 1 << 21  # density evaluations per call while building a grid


@dataclass(frozen=True)
class SunGrid:
    """Optical depth to the sun on `optical_depth` (Nw, Nv, Nu) planes, w towards the sun;
    `atlas` (1, 2, Nv + 2·PAD, Nw·(Nu + 2·PAD)): the planes side by side, for lookups, with τ in
    channel 0 and σ_t on the plane in channel 1. A world point p maps to q = p @ `to_atlas` +
    `offset` [3], clamped to [`low`, `high`] (the table's box): q = (atlas x within plane 0,
    atlas y, w in plane units), each in `grid_sample`'s normalised coordinates but w; plane k sits
    k·`plane_stride` further along atlas x, and planes are `plane_gap` apart in the world."""

    optical_depth: Tensor
    atlas: Tensor
    to_atlas: Tensor
    offset: Tensor
    low: Tensor
    high: Tensor
    plane_stride: float
    plane_gap: float

    def lookup(self, points: Tensor, sigma_t: Tensor) -> Tensor:
        """T to the sun at `points` [N, 3], whose extinction is `sigma_t` [N]. -> [N]."""
        return grid_transmittance(self.lanes(), list(points.unbind(1)), sigma_t)

    def lanes(self) -> SimpleNamespace:
        """What `grid_transmittance` takes, for this grid alone."""
        height, width = self.atlas.shape[-2:]
        return SimpleNamespace(to_atlas=[list(row) for row in self.to_atlas], offset=list(self.offset), low=list(self.low),
                               high=list(self.high), plane_stride=self.plane_stride, plane_gap=self.plane_gap,
                               atlas=self.atlas.reshape(-1), base=0, width=width, height=height, plane_size=width * height)


def grids_lanes(grids: list[SunGrid], s: Tensor, per_lane, table) -> SimpleNamespace:
    """What `grid_transmittance` takes for lanes of scenes `s` [n], one grid per scene (`grids`,
    of one shape: a batch shares its shadow settings): `per_lane` (per scene [B] or [B, C] -> a
    lane or C lanes), `table` (a flat tensor -> the lanes' table type)."""
    from drjit.llvm import Int32

    one = grids[0].lanes()
    rows = per_lane(torch.stack([g.to_atlas.reshape(9) for g in grids]))
    plane_size = one.plane_size
    return SimpleNamespace(
        to_atlas=[rows[3 * r:3 * r + 3] for r in range(3)],
        **{name: per_lane(torch.stack([getattr(g, name) for g in grids])) for name in ("offset", "low", "high")},
        plane_stride=per_lane(torch.tensor([g.plane_stride for g in grids])),
        plane_gap=per_lane(torch.tensor([g.plane_gap for g in grids])),
        atlas=table(torch.cat([g.atlas.reshape(-1) for g in grids])), base=Int32((s * 2 * plane_size).to(torch.int32).numpy()),
        width=one.width, height=one.height, plane_size=plane_size)


def _cubic(t) -> list:
    """The bicubic weights (A = −0.75, as `F.grid_sample`'s) of the four taps around fraction `t` (lanes)."""
    a = -0.75
    near = lambda x: ((a + 2.0) * x - (a + 3.0)) * x * x + 1.0  # noqa: E731
    far = lambda x: ((a * x - 5.0 * a) * x + 8.0 * a) * x - 4.0 * a  # noqa: E731
    return [far(t + 1.0), near(t), near(1.0 - t), far(2.0 - t)]


def grid_transmittance(g: SimpleNamespace, p: list, sigma_t):
    """T to the sun at lanes `p` (three) of extinction `sigma_t` (lanes, `ops.lanes`), from a
    `SunGrid` (`g`: its `lanes()`, or `grids_lanes`): τ and σ_t on the next plane towards the sun,
    interpolated bicubically where the sun ray from p meets it (`F.grid_sample`'s bicubic, border
    padding, corners aligned), plus the trapezoid over the gap."""
    m = g.to_atlas  # the affine map as multiply-adds per lane: the same for any chunking
    q = [lanes.minimum(lanes.maximum(g.offset[c] + p[0] * m[0][c] + p[1] * m[1][c] + p[2] * m[2][c], g.low[c]), g.high[c])
         for c in range(3)]
    plane = -lanes.floor(-q[2])  # the next stored plane towards the sun
    gap = (plane - q[2]) * g.plane_gap  # world distance to it
    ix = (q[0] + plane * g.plane_stride + 1.0) * 0.5 * (g.width - 1)  # atlas texels
    iy = (q[1] + 1.0) * 0.5 * (g.height - 1)
    fx, fy = lanes.floor(ix), lanes.floor(iy)
    wx, wy = _cubic(ix - fx), _cubic(iy - fy)
    x0, y0 = lanes.to_int32(fx), lanes.to_int32(fy)
    cols = [lanes.minimum(lanes.maximum(x0 + (i - 1), 0), g.width - 1) for i in range(4)]
    tau = feet = 0.0
    for j in range(4):
        row = g.base + lanes.minimum(lanes.maximum(y0 + (j - 1), 0), g.height - 1) * g.width
        taps = [row + c for c in cols]
        tau = tau + wy[j] * sum((wx[i] * lanes.gather(g.atlas, taps[i]) for i in range(1, 4)),
                                wx[0] * lanes.gather(g.atlas, taps[0]))
        feet = feet + wy[j] * sum((wx[i] * lanes.gather(g.atlas, taps[i] + g.plane_size) for i in range(1, 4)),
                                  wx[0] * lanes.gather(g.atlas, taps[0] + g.plane_size))
    # bicubic weights are negative in places: an overshoot below 0 would mean T > 1
    tau = lanes.clamp_min(tau, 0.0) + 0.5 * gap * (sigma_t + lanes.clamp_min(feet, 0.0))
    return lanes.exp(-tau)


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
    chord: Callable[[Tensor, Tensor], tuple[Tensor, Tensor]] | None = None,
) -> SunGrid:
    """Tabulate τ to the sun over the box [box_min, box_max] (each [3]).

    `extinction(points [M, 3]) -> σ_t [M]` (0 outside the medium); `resolution` nodes across the
    sun and resolution // 2 + 1 stored planes along it (integrated on twice as many). Nodes on the
    sun-side face have τ = 0 (nothing lies beyond the box towards the sun).

    `chord(origins [M, 3], directions [M, 3]) -> (t_in, t_out) [M]`, where given, is where lines
    meet the medium's bounds: only the nodes inside are evaluated, the others are 0. The box around
    a tilted box or a sphere is mostly outside it."""
    frame = sun_frame(sun_dir)
    corners = torch.stack(torch.meshgrid(*[torch.stack([box_min[i], box_max[i]]) for i in range(3)], indexing="ij"), -1)
    local = corners.reshape(-1, 3) @ frame.T  # corners in (u, v, w)
    lo, hi = local.min(dim=0).values, local.max(dim=0).values
    size = (hi - lo).clamp_min(torch.finfo(lo.dtype).tiny)
    origin = lo @ frame  # back to world
    n, planes = resolution, resolution // 2 + 1
    steps = 2 * (planes - 1)  # integration sub-planes: every second one is stored
    kw = dict(dtype=box_min.dtype, device=box_min.device)
    across = torch.linspace(0.0, 1.0, n, **kw)
    b, a = torch.meshgrid(across, across, indexing="ij")
    base = origin + (torch.stack([a * size[0], b * size[1]], -1).reshape(-1, 2)) @ frame[:2]  # [n², 3]: the back plane
    spacing = size[2] / steps
    if chord is None:
        first = torch.zeros(n * n, dtype=torch.long, device=base.device)
        count = torch.full_like(first, steps + 1)
    else:  # nodes k·spacing within [t_in, t_out] of the line from each back-plane node towards the sun
        t_in, t_out = chord(base, frame[2].expand_as(base))
        first = torch.ceil(t_in / spacing).clamp(0, steps + 1).long()
        count = (torch.floor(t_out / spacing).clamp(-1, steps).long() + 1 - first).clamp_min(0)
    column = torch.repeat_interleave(torch.arange(n * n, device=base.device), count)
    k = torch.arange(column.shape[0], device=base.device) - torch.repeat_interleave(torch.cumsum(count, 0) - count, count) + first[column]
    # every node in the chords is evaluated: testing occupancy first costs as much as the grid lookup it saves
    sigma = base.new_zeros(steps + 1, n * n)
    nodes = torch.addcmul(base[column], (k * spacing)[:, None], frame[2])
    # in chunks: a 384 grid has ~28 M nodes in a sphere, whose density intermediates took 5 GB at once
    if nodes.shape[0]:  # (a coarse grid's lines may all miss a thin medium: then it casts no shadow)
        sigma[k, column] = torch.cat([extinction(nodes[i:i + NODE_CHUNK]) for i in range(0, nodes.shape[0], NODE_CHUNK)])
    return _sun_grid(sigma.reshape(steps + 1, n, n), spacing, frame=frame, origin=origin, size=size, like=box_min)


def _sun_grid(sigma: Tensor, spacing: Tensor, *, frame: Tensor, origin: Tensor, size: Tensor, like: Tensor) -> SunGrid:
    """The `SunGrid` of σ_t on the integration sub-planes `sigma` (2·(planes − 1) + 1, n, n),
    `spacing` apart along the sun, in the box at `origin` [3] of `size` [3] in the sun `frame` (3, 3);
    its constants in the dtype and on the device of `like`."""
    n, planes = sigma.shape[-1], (sigma.shape[0] - 1) // 2 + 1
    kw = dict(dtype=like.dtype, device=like.device)
    # optical depth from stored plane k to the sun-side face: Simpson's rule on each pair of
    # sub-planes (k, k + ½, k + 1), summed from the sun side: more accurate than the trapezoid rule
    # for the same evaluations
    pairs = (sigma[0:-1:2] + 4.0 * sigma[1::2] + sigma[2::2]) * (spacing / 3.0)
    tau = torch.flip(torch.cumsum(torch.flip(pairs, [0]), 0), [0])
    tau = torch.cat([tau, torch.zeros_like(sigma[:1])], dim=0)  # (planes, n, n)
    planes_of = torch.stack([tau, sigma[::2]], dim=1)  # (planes, 2, n, n): τ and σ_t on each stored plane
    padded = F.pad(planes_of, (PAD, PAD, PAD, PAD), mode="replicate")  # (planes, 2, n + 2P, n + 2P)
    atlas = padded.permute(1, 2, 0, 3).reshape(1, 2, n + 2 * PAD, planes * (n + 2 * PAD))
    # (u, v, w) in [0, 1] of the table's box -> atlas x and y normalised for grid_sample, w in planes
    height, width = atlas.shape[-2:]
    scale = torch.tensor([2.0 * (n - 1) / (width - 1), 2.0 * (n - 1) / (height - 1), planes - 1], **kw)
    low = torch.tensor([2.0 * PAD / (width - 1) - 1.0, 2.0 * PAD / (height - 1) - 1.0, 0.0], **kw)
    to_atlas = frame.T * (scale / size)
    return SunGrid(optical_depth=tau, atlas=atlas, to_atlas=to_atlas, offset=low - origin @ to_atlas, low=low, high=low + scale,
                   plane_stride=2.0 * (n + 2 * PAD) / (width - 1), plane_gap=float(size[2]) / (planes - 1))
