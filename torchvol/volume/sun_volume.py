"""Transmittance to a sun, precomputed once per scene on a sun-aligned grid.

A shadow march per sample costs K density evaluations per lit sample. For a directional light the
optical depth τ(p) = ∫ σ_t(p + s·L) ds can instead be tabulated once: sample the extinction on
planes across the sun direction L (two sub-planes per stored plane), and accumulate τ towards the
sun with a reverse cumulative sum of Simpson's rule over each pair of sub-planes. Only the nodes
inside the medium's bounds are evaluated (`chord`). A lookup then needs
only what lies between the point and the next stored plane towards the sun:

    τ(p) = τ_plane(u, v) + ½·gap·(σ_t(p) + σ_plane(u, v)),

with τ_plane and σ_plane (σ_t where the sun ray from p meets that plane) interpolated bicubically
inside the plane (`F.grid_sample`'s bicubic, written in lanes: `grid_transmittance`). Interpolating
across L is what costs accuracy: bicubic planes are closer to the exact transmittance than
trilinear interpolation of the same table, and the gap term removes the interpolation along L
(docs/VOLUMES.md has the figures). Cost: one density evaluation per table node; a lookup needs none.

Built two ways from one layout (`grid_layout`): eagerly (`grid_atlas`, the reference) or as one
Dr.Jit kernel for a whole batch (`volume.density_lanes.sun_grid_kernel`), each column of nodes a
loop towards the sun that writes its planes straight into the atlas.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace
from typing import Callable

import torch
from torch import Tensor

from ..ops import lanes
from ..schema.batch import take

NODE_CHUNK = 1 << 21  # density evaluations per call while building a grid


@dataclass(frozen=True)
class GridLayout:
    """Where one scene's sun grid has its nodes: the sun `frame` (3, 3) (rows u, v, w; w the sun
    direction), the table's box at `origin` [3] (world) of `size` [3] (in the frame), `n` nodes
    across the sun on each of `planes` stored planes along it, integrated on 2·(planes − 1)
    sub-planes `spacing` apart; the back plane's nodes `base` [n², 3] (v-major), and of the
    sub-planes k·`spacing` along each node's line towards the sun, those from `first` [n²] on,
    `count` [n²] of them, lie inside the medium (the others are 0 and never evaluated)."""

    frame: Tensor
    origin: Tensor
    size: Tensor
    spacing: Tensor
    base: Tensor
    first: Tensor
    count: Tensor
    n: int
    planes: int


@dataclass(frozen=True)
class SunGrid:
    """Optical depth to the sun, a table per scene of a batch (B scenes): `atlas`
    [B·2·n·planes·n] holds, per scene, τ (channel 0) and σ_t (channel 1) on `planes` stored planes
    of n × n nodes, w towards the sun, laid (v, plane, u, channel): a node's two values side by
    side, read together by one 64-bit gather in a kernel (`lanes.gather_pair`). A world point p of scene b
    maps to q = p @ `to_atlas`[b] + `offset`[b] (to_atlas (B, 3, 3), offset (B, 3)), clamped to
    [0, (n − 1, n − 1, planes − 1)]: u and v in texels of a plane, w in planes; the planes are
    `plane_gap` [B] apart in the world."""

    atlas: Tensor
    to_atlas: Tensor
    offset: Tensor
    plane_gap: Tensor
    n: int
    planes: int

    def lookup(self, points: Tensor, sigma_t: Tensor, s: Tensor | None = None) -> Tensor:
        """T to the sun at `points` [N, 3] of scenes `s` [N] (None: the first), whose extinction is
        `sigma_t` [N]. -> [N]."""
        s = torch.zeros(points.shape[0], dtype=torch.long, device=points.device) if s is None else s
        per_lane = lambda x: take(x, s) if x.ndim == 1 else list(take(x, s).unbind(1))  # noqa: E731
        return grid_transmittance(self.lanes(s, per_lane, lambda t: t, lambda t: t), list(points.unbind(1)), sigma_t)

    def lanes(self, s: Tensor, per_lane, pairs, ints) -> SimpleNamespace:
        """What `grid_transmittance` takes for lanes of scenes `s` [n]: `per_lane` (per scene [B]
        or [B, C] -> a lane or C lanes), `pairs` (the atlas's (τ, σ_t) pairs [B·n·planes·n, 2] ->
        the table `lanes.gather_pair` reads: themselves eagerly, `lanes.pairs_of` in a kernel),
        `ints` (an int32 tensor [n] -> an int lane)."""
        rows = per_lane(self.to_atlas.reshape(-1, 9))
        return SimpleNamespace(
            to_atlas=[rows[3 * r:3 * r + 3] for r in range(3)], offset=per_lane(self.offset),
            high=[float(self.n - 1), float(self.n - 1), float(self.planes - 1)], plane_gap=per_lane(self.plane_gap),
            pairs=pairs(self.atlas.view(-1, 2)), base=ints((s * (self.n * self.planes * self.n)).to(torch.int32)),
            n=self.n, row=self.planes * self.n)


def _cubic(t) -> list:
    """The bicubic weights (A = −0.75, as `F.grid_sample`'s) of the four taps around fraction `t` (lanes)."""
    a = -0.75
    near = lambda x: ((a + 2.0) * x - (a + 3.0)) * x * x + 1.0  # noqa: E731
    far = lambda x: ((a * x - 5.0 * a) * x + 8.0 * a) * x - 4.0 * a  # noqa: E731
    return [far(t + 1.0), near(t), near(1.0 - t), far(2.0 - t)]


def grid_transmittance(g: SimpleNamespace, p: list, sigma_t):
    """T to the sun at lanes `p` (three) of extinction `sigma_t` (lanes, `ops.lanes`), from a
    `SunGrid`'s `lanes`: τ and σ_t on the next plane towards the sun, interpolated bicubically
    where the sun ray from p meets it (`F.grid_sample`'s bicubic, its border rule: the taps past a
    plane's edge repeat the edge), plus the trapezoid over the gap."""
    m = g.to_atlas  # the affine map as multiply-adds per lane: the same for any chunking
    q = [lanes.minimum(lanes.maximum(g.offset[c] + p[0] * m[0][c] + p[1] * m[1][c] + p[2] * m[2][c], 0.0), g.high[c])
         for c in range(3)]
    plane = -lanes.floor(-q[2])  # the next stored plane towards the sun
    gap = (plane - q[2]) * g.plane_gap  # world distance to it
    fx, fy = lanes.floor(q[0]), lanes.floor(q[1])  # texels within a plane: small numbers, exact fractions
    wx, wy = _cubic(q[0] - fx), _cubic(q[1] - fy)
    x0, y0 = lanes.to_int32(fx), lanes.to_int32(fy)
    first = g.base + lanes.to_int32(plane) * g.n
    cols = [first + lanes.minimum(lanes.maximum(x0 + (i - 1), 0), g.n - 1) for i in range(4)]
    tau = feet = 0.0
    for j in range(4):
        row = lanes.minimum(lanes.maximum(y0 + (j - 1), 0), g.n - 1) * g.row
        taps = [lanes.gather_pair(g.pairs, row + c) for c in cols]  # (τ, σ_t) of each tap
        tau = tau + wy[j] * sum((wx[i] * taps[i][0] for i in range(1, 4)), wx[0] * taps[0][0])
        feet = feet + wy[j] * sum((wx[i] * taps[i][1] for i in range(1, 4)), wx[0] * taps[0][1])
    # bicubic weights are negative in places: an overshoot below 0 would mean T > 1
    tau = lanes.clamp_min(tau, 0.0) + 0.5 * gap * (sigma_t + lanes.clamp_min(feet, 0.0))
    return lanes.exp(-tau)


def simpson(lo, mid, hi, spacing):
    """Optical depth over a pair of sub-planes by Simpson's rule: σ_t on the planes `lo`, `mid`,
    `hi` (`spacing` apart), lanes. More accurate than the trapezoid rule for the same evaluations."""
    return (lo + 4.0 * mid + hi) * (spacing / 3.0)


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


def grid_layout(box_min: Tensor, box_max: Tensor, sun_dir: Tensor, *, resolution: int,
                chord: Callable[[Tensor, Tensor], tuple[Tensor, Tensor]] | None = None) -> GridLayout:
    """The `GridLayout` of a table over the box [box_min, box_max] (each [3]) towards the sun
    `sun_dir` [3]: `resolution` nodes across the sun, resolution // 2 + 1 stored planes along it
    (integrated on twice as many). `chord(origins [M, 3], directions [M, 3]) -> (t_in, t_out)
    [M]`, where given, is where lines meet the medium's bounds: only the nodes inside are
    evaluated. The box around a tilted box or a sphere is mostly outside it."""
    frame = sun_frame(sun_dir)
    corners = torch.stack(torch.meshgrid(*[torch.stack([box_min[i], box_max[i]]) for i in range(3)], indexing="ij"), -1)
    local = corners.reshape(-1, 3) @ frame.T  # corners in (u, v, w)
    lo, hi = local.min(dim=0).values, local.max(dim=0).values
    size = (hi - lo).clamp_min(torch.finfo(lo.dtype).tiny)
    origin = lo @ frame  # back to world
    n, planes = resolution, resolution // 2 + 1
    steps = 2 * (planes - 1)  # integration sub-planes: every second one is stored
    across = torch.linspace(0.0, 1.0, n, dtype=box_min.dtype, device=box_min.device)
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
    return GridLayout(frame, origin, size, spacing, base, first, count, n, planes)


def grid_atlas(extinction: Callable[[Tensor], Tensor], layout: GridLayout) -> Tensor:
    """One scene's table of a `SunGrid`'s atlas [2·n·planes·n], eagerly: `extinction(points
    [M, 3]) -> σ_t [M]` on the nodes inside the medium (`layout`), τ accumulated from the sun's
    side by `simpson` over each pair of sub-planes. Nodes on the sun-side face have τ = 0 (nothing
    lies beyond the box towards the sun)."""
    g, n = layout, layout.n
    steps = 2 * (g.planes - 1)
    column = torch.repeat_interleave(torch.arange(n * n, device=g.base.device), g.count)
    k = torch.arange(column.shape[0], device=g.base.device) - torch.repeat_interleave(torch.cumsum(g.count, 0) - g.count, g.count) + g.first[column]
    # every node in the chords is evaluated: testing occupancy first costs as much as the grid lookup it saves
    sigma = g.base.new_zeros(steps + 1, n * n)
    nodes = torch.addcmul(g.base[column], (k * g.spacing)[:, None], g.frame[2])
    # in chunks: a 384 grid has ~28 M nodes in a sphere, whose density intermediates took 5 GB at once
    if nodes.shape[0]:  # (a coarse grid's lines may all miss a thin medium: then it casts no shadow)
        sigma[k, column] = torch.cat([extinction(nodes[i:i + NODE_CHUNK]) for i in range(0, nodes.shape[0], NODE_CHUNK)])
    pairs = simpson(sigma[0:-1:2], sigma[1::2], sigma[2::2], g.spacing)
    tau = torch.cat([torch.flip(torch.cumsum(torch.flip(pairs, [0]), 0), [0]), torch.zeros_like(sigma[:1])])
    return torch.stack([tau, sigma[::2]]).reshape(2, g.planes, n, n).permute(2, 1, 3, 0).reshape(-1)  # (v, plane, u, channel)


def sun_grid(layouts: list[GridLayout], atlas: Tensor) -> SunGrid:
    """The `SunGrid` of a batch's tables: the scenes' `layouts` (of one n and planes) and their
    atlases one after the other, `atlas` [B·2·n·planes·n]."""
    n, planes = layouts[0].n, layouts[0].planes
    maps = []
    for g in layouts:
        scale = torch.tensor([n - 1.0, n - 1.0, planes - 1.0], dtype=g.base.dtype, device=g.base.device)
        maps.append(g.frame.T * (scale / g.size))  # (u, v, w) of the table's box -> texels, texels, planes
    to_atlas = torch.stack(maps)
    offset = -torch.stack([g.origin @ m for g, m in zip(layouts, maps)])
    return SunGrid(atlas=atlas, to_atlas=to_atlas, offset=offset,
                   plane_gap=torch.stack([g.size[2] / (planes - 1) for g in layouts]), n=n, planes=planes)


def sun_transmittance_grid(extinction: Callable[[Tensor], Tensor], box_min: Tensor, box_max: Tensor, sun_dir: Tensor, *,
                           resolution: int, chord: Callable[[Tensor, Tensor], tuple[Tensor, Tensor]] | None = None) -> SunGrid:
    """Tabulate τ to the sun over the box [box_min, box_max] (each [3]) for one scene, eagerly
    (`grid_layout`, `grid_atlas`): `extinction(points [M, 3]) -> σ_t [M]` (0 outside the medium)."""
    layout = grid_layout(box_min, box_max, sun_dir, resolution=resolution, chord=chord)
    return sun_grid([layout], grid_atlas(extinction, layout))
