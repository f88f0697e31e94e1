"""A volume's density as a Dr.Jit kernel evaluates it: the kind's ``lanes`` inputs and function
(`fields.DENSITIES`), the bounds' and the edge fade's, the per-scene tables gathered per lane; the
density alone over points (the bench's floor) and the sun's grids built from it
(`sun_grid_kernel`). What marches with it is `kernel_march`; the shadow module builds its grids
here without importing the march.
"""

from __future__ import annotations

from collections.abc import Callable
from types import SimpleNamespace

import torch
from torch import Tensor

from ..fields import DENSITIES
from ..fields.base import DENSITY_MAX
from ..fields.edge import EdgeField, faded
from ..geometry.bounds import bounds_lanes
from ..ops import lanes
from ..runtime.threads import set_drjit_threads
from ..schema.batch import take
from .sun_volume import GridLayout, simpson


def has_lanes(vol) -> bool:
    """Whether the volume's density kind is written in lanes for this variant (`fields.DENSITIES`)."""
    kind = DENSITIES[vol.density.kind].caps.get("lanes")
    return kind is not None and (len(kind) < 3 or kind[2](vol))


def field_inputs(vol, s: Tensor, per_ray) -> SimpleNamespace:
    """What the volume's density takes per lane, for points of scenes `s` [n] (`per_ray`: per
    scene -> per lane): its kind's lanes inputs (`fields.DENSITIES`' ``lanes``), the bounds', the edge's."""

    inner, edge = inner_and_edge(vol)
    inputs, density = DENSITIES[vol.params.density.kind].caps["lanes"][:2]
    return SimpleNamespace(
        field=inputs(inner, lanes.lanes_inputs(s, per_ray)), field_density=density, bounds=bounds_lanes(vol.params.bounds.value, per_ray),
        edge=None if edge is None else SimpleNamespace(width=per_ray(edge.width),
                                                       base=None if edge.base is None else per_ray(edge.base)))


def density_lanes(k: SimpleNamespace, vol) -> Callable:
    """The volume's density over its `field_inputs` `k`: density(p, count) at lanes `p` (three),
    `count` octaves kept or None: the field clamped at 0, faded at the edge and capped, as
    `renderer.stats.CountedField` reads it."""
    depth_in = vol.bounds.caps["lanes"][1]

    def density(p, count):
        raw = lanes.clamp_min(k.field_density(k.field, p, count), 0.0)
        if k.edge is not None:
            depth = depth_in(k.bounds, p)
            if k.edge.base is not None:
                depth = lanes.minimum(depth, p[1] - k.edge.base)
            raw = faded(raw, depth, k.edge.width)
        return lanes.clamp_max(raw, DENSITY_MAX)

    return density


def crossing(vol, s: Tensor, per_ray) -> SimpleNamespace:
    """Volume `vol` as a ray crossing it sees it, for lanes of scenes `s` [n]: its density
    (`density_lanes`), its bounds' interval(p, direction) -> (near, far), σ_t per lane, its reach and
    index, and where its plan has a `line_integral`, depth(p, direction, length, start=None): ∫
    density along the line in closed form from the density `start` at p (None: evaluated there;
    `shadow.line_depth`'s), else None."""
    import drjit as dr
    from drjit.llvm import Float

    k = field_inputs(vol, s, per_ray)
    interval = vol.bounds.caps["lanes"][0]
    density = density_lanes(k, vol)
    closed = DENSITIES[vol.params.density.kind].caps["optical_depth"] if vol.plan.line_integral else None
    return SimpleNamespace(density=density, interval=lambda p, d: interval(k.bounds, p, d),
                           sigma_t=per_ray(vol.params.sigma_t), reach=dr.opaque(Float, min(vol.plan.reach, 3e38)),
                           index=vol.plan.index, octaves=getattr(k.field, "octaves", None),
                           depth=None if closed is None else lambda p, d, length, start=None: closed(
                               k.field, density(p, None) if start is None else start, d, length))


def density_kernel(vol, points: Tensor, scene: Tensor | None = None, kept: Tensor | None = None) -> Callable[[], Tensor]:
    """The volume's density alone at `points` [N, 3] of scenes `scene` [N] (None: scene 0), each
    with its octaves `kept` [N] (None: all), as one Dr.Jit kernel: the march's floor (`torchvol
    bench speed`: what the march would cost if nothing but its density did). -> a function that
    evaluates it once, returning [N]."""
    import drjit as dr

    s = torch.zeros(points.shape[0], dtype=torch.long) if scene is None else scene
    density = density_lanes(field_inputs(vol, s, lambda x: lanes.lanes_of(take(x, s), lanes.floats_of)), vol)
    p, count = lanes.lanes_of(points, lanes.floats_of), None if kept is None else lanes.ints_of(kept)

    def run() -> Tensor:
        set_drjit_threads()
        out = density(p, count)
        dr.eval(out)
        dr.sync_thread()
        return lanes.tensor_of(out)

    return run


def sun_grid_kernel(vol, layouts: list[GridLayout]) -> Tensor:
    """The atlases of volume `vol`'s sun grids, one a scene (`layouts`, from `sun_volume.grid_layout`),
    as one Dr.Jit kernel: a loop per column of nodes from the sun's side, σ_t at each node inside
    the medium (`density_lanes`, as `sun_volume.grid_atlas` has the field evaluate it), τ summed by
    `simpson` in float64 (as torch's cumsum sums float32), each stored plane written straight into
    the atlas. -> (the atlases one after the other [B·2·n·planes·n], the nodes evaluated)."""
    import drjit as dr
    from drjit.llvm import Float, Float64, Int32, UInt32, UInt64

    set_drjit_threads()
    n, planes, batch = layouts[0].n, layouts[0].planes, len(layouts)
    s = torch.arange(batch).repeat_interleave(n * n)
    per_ray = lanes.per_scene_lanes(s)
    density, sigma_t = density_lanes(field_inputs(vol, s, per_ray), vol), per_ray(vol.params.sigma_t)
    base = lanes.lanes_of(torch.cat([g.base for g in layouts]), lanes.floats_of)
    toward = per_ray(torch.stack([g.frame[2] for g in layouts]))
    spacing = per_ray(torch.stack([g.spacing for g in layouts]))
    first = lanes.ints_of(torch.cat([g.first for g in layouts]))
    stop = first + lanes.ints_of(torch.cat([g.count for g in layouts]))
    column = dr.arange(Int32, batch * n * n)
    channel = n * planes * n
    # (v, plane, u) of each scene's (τ, σ_t) pairs, each one 64-bit word (τ in its low half): the
    # column's u and v, its plane added as it is written, one scatter a node
    at = (column // (n * n)) * channel + ((column // n) % n) * (planes * n) + column % n
    atlas = dr.empty(UInt64, batch * channel)  # every (column, plane) is written below: no memset (3 ms a 192 grid)

    def sigma(k):
        """σ_t at sub-plane `k` (an Int32 lane) of each column, 0 outside the medium."""
        kf = Float(k) * spacing
        inside = (k >= first) & (k < stop)
        return dr.if_stmt((), inside, lambda: sigma_t * density([dr.fma(kf, toward[c], base[c]) for c in range(3)], None),
                          lambda: dr.zeros(Float, dr.width(kf)))

    def write(plane, tau, sig):
        bits = lambda x: UInt64(dr.reinterpret_array(UInt32, x))  # noqa: E731
        dr.scatter(atlas, bits(Float(tau)) | (bits(sig) << 32), at + plane * n)

    top = dr.full(Int32, planes - 1, dr.width(column))
    hi = sigma(2 * top)
    write(top, dr.zeros(Float64, dr.width(hi)), hi)

    def step(plane, tau, hi):
        lo = sigma(2 * plane - 2)
        tau = tau + Float64(simpson(lo, sigma(2 * plane - 1), hi, spacing))
        write(plane - 1, tau, lo)
        return plane - 1, tau, lo

    dr.while_loop((top, dr.zeros(Float64, dr.width(hi)), hi), lambda plane, *_: plane > 0, step, mode="symbolic")
    dr.eval(atlas)
    dr.sync_thread()
    return lanes.tensor_of(atlas).view(torch.float32), int(sum(int(g.count.sum()) for g in layouts))


def writes_in_lanes(vol) -> bool:
    """Whether the volume's density and bounds are written in lanes (a kernel can evaluate it)."""
    return has_lanes(vol.params) and "lanes" in vol.bounds.caps


def inner_and_edge(vol):
    """The volume's density field and its `Edge` tables (None: no edge fade) under its counted field."""
    field = vol.field.inner
    return (field.inner, field.edge) if isinstance(field, EdgeField) else (field, None)


__all__ = ["density_kernel", "density_lanes", "field_inputs", "has_lanes", "inner_and_edge",
           "crossing", "sun_grid_kernel", "writes_in_lanes"]
