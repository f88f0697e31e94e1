"""A smooth SDF terrain, sphere traced (not voxels): the heightfield

    y = base + amplitude · fbm(frequency · (x, 0, z))     (value noise in [−1, 1], per-scene seed)

Its signed vertical gap g(p) = p.y − h(p.x, p.z) bounds the distance to the surface from above by
a factor of the slope; a sphere-tracing step of `safety · g` (the Lipschitz safety factor) never
crosses it where the slope is below √(1/safety² − 1) (1.73 at 0.5), and a step that does
overshoot a steeper slope is pulled back to the secant root between its last two points. Rays are traced only through the slab the heights can reach
(|fbm| < 1), so a shadow ray that leaves it upwards is done at once.

The surface is Lambert-shaded by the lights: grass `color` blended to `rock_color` on steep slopes,
`ambient` (the sky light) plus each light's n·l irradiance, times its visibility where the light
casts shadows (`lights[i].shadow`): the terrain itself and every volume the shadow ray crosses
(`transmittance` from the render, see `volume/shadow.py: occluder_transmittance`). Where the scene
has volumes, the sky light has its visibility too (`ambient_visibility = "march"`): the
transmittance of one ray straight up (the zenith, where the sky is brightest) through every
volume, so ground under a cloud or in fog gets less of it; a heightfield never rises over its own
zenith, so the terrain itself cannot block that ray. It outputs hit distance, colour and the
`normal` AOV, like the voxel surface, and the volumes march up to its hit.
"""

from __future__ import annotations

import math
from contextlib import nullcontext
from functools import partial
from types import SimpleNamespace
from typing import Annotated, Callable, Literal, Sequence

import torch
from pydantic import Field, field_validator
from torch import Tensor

from .fields.fbm import Hash
from .fields.heightfield import (
    height_lanes,
    normal_lanes,
    onto_surface,
    terrain_lanes,
    trace_lanes,
    trace_step,
    visible_lanes,
)
from .geometry.rays import clip_to_ray, intersect_slab
from .geometry.scatter import lambert_bounce, lambert_reflect
from .geometry.surface_hit import SurfaceHit
from .ops import lanes
from .ops.mathops import take_rows
from .schema.batch import Stacked, take
from .schema.models import EACH, Strict, Vec3, nonneg


class Terrain(Strict):
    """A sphere-traced heightfield y = base + amplitude · fbm(frequency · (x, 0, z)) (value noise,
    `octaves` octaves, gain 0.5, in (−1, 1)), Lambert-shaded: `color` on flat ground, `rock_color`
    where 1 − n.y exceeds `rock_slope` (a 0.1-wide blend), plus `ambient`. `steps` sphere-tracing
    steps of `safety` · (y − h) per primary and shadow ray, hits where the gap is under
    `epsilon` · (1 + t), rays traced up to `max_distance`; shadow rays start `shadow_offset` above
    the hit along the normal. `ambient_visibility`: "march" (where the scene has volumes, the
    `ambient` is times the transmittance straight up through them, `ambient_steps` equal steps
    over each volume's chord) or "none" (the `ambient` everywhere)."""

    seed: Annotated[int, EACH] = 0
    hash: Hash = "table"  # its value noise's lattice hash, as `density.fbm.hash`
    base: float = 0.0
    amplitude: float = Field(1.0, ge=0.0)
    frequency: float = Field(0.5, gt=0.0, le=1e6)
    octaves: int = Field(5, ge=1, le=12)
    color: Vec3 = (0.3, 0.45, 0.18)
    rock_color: Vec3 = (0.45, 0.4, 0.35)
    rock_slope: float = Field(0.3, ge=0.0, le=1.0)
    ambient: Vec3 = (0.1, 0.12, 0.15)
    steps: int = Field(128, ge=1, le=100_000)
    safety: float = Field(0.5, gt=0.0, le=1.0)
    epsilon: float = Field(1e-3, gt=0.0, le=0.1)
    max_distance: float = Field(200.0, gt=0.0)
    shadow_offset: float = Field(0.01, ge=0.0)
    ambient_visibility: Literal["march", "none"] = "march"
    ambient_steps: int = Field(8, ge=1, le=256)

    _c = field_validator("color", "rock_color", "ambient")(lambda v: nonneg(v))


TERRAIN_AOVS = ("normal",)


def height(t: Stacked, xz: Tensor, s: Tensor) -> Tensor:
    """Terrain height [n] at horizontal points `xz` [n, 2] of scenes `s` [n] (`height_lanes` on torch)."""
    return height_lanes(_torch_lanes(t, s, xz), xz[:, 0], xz[:, 1])


def _torch_lanes(t: Stacked, s: Tensor, like: Tensor):
    """`terrain_lanes` of scenes `s` [n] on torch columns (the eager reference), in `like`'s dtype and device."""
    to = SimpleNamespace(per_lane=lambda v: take(v, s), scene=s, number=lambda c: c,
                         ints=lambda v: v.to(device=like.device, dtype=torch.int32), floats=lambda v: v.to(like))
    return terrain_lanes(t, to, like.dtype)


def gap(t: Stacked, p: Tensor, s: Tensor) -> Tensor:
    """Signed vertical distance [n] of points `p` [n, 3] above the terrain."""
    return p[:, 1] - height(t, p[:, [0, 2]], s)


def span(t: Stacked, o: Tensor, d: Tensor, s: Tensor, t_max: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(t0, t1, crosses) [n]: where rays `o`, `d` [n, 3] are inside the slab of reachable heights,
    up to `t_max` [n] and `max_distance`."""
    base, amp = take(t.base, s), take(t.amplitude, s)
    pad = 1e-3 * (1.0 + amp)  # a flat terrain's slab has no thickness
    t_near, t_far = intersect_slab(o, d, base - amp - pad, base + amp + pad)
    return clip_to_ray(t_near, t_far, torch.minimum(t_max, take(t.max_distance, s)))


def underground(t: Stacked, o: Tensor, s: Tensor) -> Tensor:
    """[n] bool: where points `o` [n, 3] of scenes `s` [n] lie below the terrain (only points
    under the highest reachable height are looked up)."""
    below = torch.zeros(o.shape[0], dtype=torch.bool, device=o.device)
    low = (o[:, 1] < take(t.base, s) + take(t.amplitude, s)).nonzero().squeeze(1)
    if low.numel():
        below[low] = gap(t, o[low], s[low]) < 0
    return below


def trace(t: Stacked, o: Tensor, d: Tensor, s: Tensor, t_max: Tensor, *, steps: int,
          refine: bool = False) -> tuple[Tensor, Tensor]:
    """Sphere-trace rays `o`, `d` [n, 3] (d unit) of scenes `s` [n] to the terrain, no farther than
    `t_max` [n] -> (hit [n] bool, t [n]). Finished rays are compacted out of the loop. `refine`: a
    hit's t takes one secant step onto the surface (the hit rule stops up to ε·(1 + t) short of it:
    depth labels belong on the surface; exact on a plane)."""
    t0, t1, live = span(t, o, d, s, t_max)
    dist = torch.where(live, t0, torch.zeros_like(t0))
    hit = underground(t, o, s)  # the ground is solid: a ray that starts in it meets it at 0
    dist = torch.where(hit, torch.zeros_like(dist), dist)
    ids = (live & ~hit).nonzero().squeeze(1)
    last_t = last_g = dist[ids]  # the previous point of each live ray (for the overshoot secant)
    safety, eps = take(t.safety, s), take(t.epsilon, s)
    for step in range(steps):
        if ids.numel() == 0:
            break
        q = SimpleNamespace(safety=safety[ids], epsilon=eps[ids], height=lambda x, z, i=ids: height(t, torch.stack([x, z], 1), s[i]))
        done, ti, nxt, g = trace_step(q, o[ids].unbind(1), d[ids].unbind(1), dist[ids], last_t, last_g, step == 0)
        dist[ids] = ti
        hit[ids[done]] = True
        keep = ~done & (nxt <= t1[ids])
        dist[ids[keep]] = nxt[keep]
        ids, last_t, last_g = ids[keep], ti[keep], g[keep]
    if refine:
        dist = _onto_surface(t, o, d, s, hit, dist)
    return hit, dist


def _onto_surface(t: Stacked, o: Tensor, d: Tensor, s: Tensor, hit: Tensor, dist: Tensor) -> Tensor:
    """`onto_surface` of each hit [n] from dist [n]; the others stay."""
    ids = hit.nonzero().squeeze(1)
    if ids.numel() == 0:
        return dist
    rule = SimpleNamespace(epsilon=take(t.epsilon, s[ids]), height=lambda x, z: height(t, torch.stack([x, z], 1), s[ids]))
    out = dist.clone()
    out[ids] = onto_surface(rule, o[ids].unbind(1), d[ids].unbind(1), dist[ids])
    return out


def normal(t: Stacked, p: Tensor, s: Tensor) -> Tensor:
    """Unit surface normal [n, 3] at points `p` [n, 3] on the terrain (`normal_lanes` on torch)."""
    return torch.stack(normal_lanes(_torch_lanes(t, s, p), p[:, 0], p[:, 2]), dim=1)


def visibility(t: Stacked, p: Tensor, direction: Tensor, s: Tensor, distance: Tensor, *, steps: int) -> Tensor:
    """1 where the ray from `p` [n, 3] along `direction` [n, 3] reaches `distance` [n] (inf: a sun)
    without meeting the terrain, else 0 -> [n]."""
    hit, _ = trace(t, p, direction, s, distance, steps=steps)
    return (~hit).to(p.dtype)


def _kernel_lanes(t: Stacked, s: Tensor):
    """`terrain_lanes` of scenes `s` [n] as a Dr.Jit kernel takes them, and the torch -> lanes map
    of per-point tensors ([n] one lane; [n, 3] three, read from its rows as they lie), and of
    per-scene ones (B,) or (B, C) (gathered in the kernel: no [n] copy made in torch first)."""
    from .runtime.threads import set_drjit_threads

    set_drjit_threads()
    per_scene = lanes.per_scene_lanes(s)
    columns = lambda x: lanes.floats_of(x) if x.ndim == 1 else lanes.vector_lanes(x)  # noqa: E731
    return terrain_lanes(t, lanes.lanes_inputs(s, per_scene), torch.float32), columns, per_scene


def _to_torch(values, like: Tensor) -> list[Tensor]:
    """Evaluated Dr.Jit lanes -> torch tensors on `like`'s device."""
    import drjit as dr

    dr.eval(*values)
    dr.sync_thread()
    return [lanes.tensor_of(v).to(like.device) for v in values]


def trace_kernel(t: Stacked, o: Tensor, d: Tensor, s: Tensor) -> tuple[Tensor, Tensor]:
    """`trace` of primary rays `o`, `d` [n, 3] of scenes `s` [n] (no farther than the terrain's
    reach, the hit refined onto the surface) as one Dr.Jit kernel (`trace_lanes`): float32 on the
    CPU. -> (hit [n] bool, t [n])."""
    q, columns, _ = _kernel_lanes(t, s)
    hit, dist = _to_torch(trace_lanes(q, columns(o), columns(d), math.inf, refine=True), o)
    return hit, dist.to(o)


def normal_kernel(t: Stacked, p: Tensor, s: Tensor) -> Tensor:
    """`normal` at points `p` [n, 3] of scenes `s` [n] as one Dr.Jit kernel (`normal_lanes`). -> [n, 3]."""
    import drjit as dr

    q, columns, _ = _kernel_lanes(t, s)
    rows = lanes.interleaved(normal_lanes(q, columns(p[:, 0]), columns(p[:, 2])))
    dr.eval(rows)
    return lanes.rows_of(rows, 3).to(p)


def _look(t: Stacked, per_lane) -> SimpleNamespace:
    """The terrain's Lambert albedo at a unit normal (`color` blended to `rock_color` where
    1 − n.y passes `rock_slope`) and where a shadow or bounce ray leaves a hit at distance `t`:
    `shadow_offset` plus the hit rule's width there off the surface, lanes (`per_lane`: per scene
    -> lanes). The marched shading's and the path tracer's one source."""
    color, rock_color, slope = per_lane(t.color), per_lane(t.rock_color), per_lane(t.rock_slope)
    offset, epsilon = per_lane(t.shadow_offset), per_lane(t.epsilon)

    def albedo(n: list) -> list:
        rock = lanes.clamp((1.0 - n[1] - slope) * 10.0, 0.0, 1.0)
        return [lanes.lerp(a, b, rock) for a, b in zip(color, rock_color)]

    def lift(x: list, n: list, dist) -> list:
        off = offset + 2.0 * epsilon * (1.0 + dist)  # clear of the hit rule's width at this distance
        return [x[c] + off * n[c] for c in range(3)]

    return SimpleNamespace(albedo=albedo, lift=lift)


def path_surface(t: Stacked, s: Tensor, per_lane, like: Tensor, *, kernel: bool) -> SimpleNamespace:
    """The terrain as the path tracer's opaque surface (`volume.path`) for rays of scenes `s` [n],
    lanes (`per_lane`: per scene -> lanes; `kernel`: Dr.Jit's, else torch columns like `like`):
    `hit(o, d, t_max)` -> (the refined hit's t (inf: none), no facts), `normal(x, facts)`, and
    `_look`'s `albedo(n, facts)`, `lift(x, n, t, facts)`, `visible(p, direction, distance)` -> 1 or 0; it
    emits nothing (`emitted` None); Lambert (`geometry.scatter.lambert_reflect` of 1: a light's a·E·cos θ,
    as the marched terrain shades it; `lambert_bounce`)."""
    q = _kernel_lanes(t, s)[0] if kernel else _torch_lanes(t, s, like)
    look = _look(t, per_lane)
    if kernel:
        def hit(o, d, t_max):
            found, dist = trace_lanes(q, o, d, t_max, refine=True)
            return lanes.where(found, dist, math.inf), []

        visible = lambda p, direction, distance: visible_lanes(q, p, direction, distance)  # noqa: E731
    else:  # eagerly `trace`, which compacts finished rays out of its loop (the same step and rules)
        stack = lambda x: torch.stack(x, dim=1)  # noqa: E731
        reach = lambda x: x if isinstance(x, Tensor) else torch.full_like(like, x)  # noqa: E731

        def hit(o, d, t_max):
            found, dist = trace(t, stack(o), stack(d), s, reach(t_max), steps=int(t.steps), refine=True)
            return torch.where(found, dist, math.inf), []

        def visible(p, direction, distance):
            return visibility(t, stack(p), stack(direction), s, reach(distance), steps=int(t.steps))

    return SimpleNamespace(hit=hit, normal=lambda x, facts: normal_lanes(q, x[0], x[2]),
                           albedo=lambda n, facts: look.albedo(n), emitted=None,
                           lift=lambda x, n, dist, facts: look.lift(x, n, dist), visible=visible,
                           reflect=lambert_reflect(1.0), bounce=lambert_bounce)


def _colour(look: SimpleNamespace, n: list, ambient: list, sky, lights: list) -> list:
    """A hit's colour (three lanes): `look`'s albedo at the unit normal `n` (three lanes) times its
    light: `ambient` (three lanes) times the sky's visibility `sky` (a lane; None: 1) plus each
    light's irradiance times n·l times what its shadow lets through (`lights`: (direction,
    irradiance, visible(lit) -> lit × visibility), the vectors three lanes each). The eager
    shading's and the kernel's one source."""
    light = ambient if sky is None else [a * sky for a in ambient]
    for direction, irradiance, visible in lights:
        lit = visible(lanes.clamp_min(lanes.dot3(n, direction), 0.0))
        light = [a + e * lit for a, e in zip(light, irradiance)]
    return [a * b for a, b in zip(look.albedo(n), light)]


class TerrainSurface:
    """One batch's terrain (`params`: the batch's `Stacked` terrain) lit by `lights`; `plan` the
    batch's `TerrainPass`; `aovs` the AOV names to output; `transmittance(use, p, s, direction,
    distance, times=None) -> [n]` `times` × what a shadow ray of LightPass `use` sees (volumes and
    terrain), traced only where `times` > 0; `kernels`: the tracing and shading as Dr.Jit kernels,
    the shadow and sky rays inside the shading's where `occluder_lanes(uses, s)` gives their lanes
    (`volume.kernel_march.surface_lanes_of`: by the key of each LightPass of `uses`; None: they
    take `transmittance`)."""

    def __init__(self, params: Stacked, lights: Sequence, plan, aovs: Sequence[str],
                 transmittance: Callable[..., Tensor], kernels: bool = False,
                 occluder_lanes: Callable[..., SimpleNamespace | None] | None = None):
        self.p, self.lights, self.plan, self.transmittance, self.kernels = params, list(lights), plan, transmittance, kernels
        self.occluder_lanes = occluder_lanes
        self.aov_names = [a for a in aovs if a in TERRAIN_AOVS]

    def visibility(self, p: Tensor, direction: Tensor, s: Tensor, distance: Tensor) -> Tensor:
        """`visibility` [n] of points p [n, 3] of scenes s [n] along `direction` [n, 3] up to
        `distance` [n], with the terrain's own step count."""
        return visibility(self.p, p, direction, s, distance, steps=self.p.steps)

    def run(self, o: Tensor, d: Tensor, s: Tensor, background: Tensor,
            section: Callable[[str], object] = lambda name: nullcontext()) -> SurfaceHit:
        """o, d [n, 3] world rays (d unit); s [n] scenes; background [n, 3] -> hit, t (inf: miss)
        [n], color [n, 3] (the background where missed) and the AOVs."""
        p, n = self.p, o.shape[0]
        with section("terrain.trace"):
            if self.kernels:  # one Dr.Jit kernel, the same rules
                hit, t = trace_kernel(p, o, d, s)
            else:
                hit, t = trace(p, o, d, s, torch.full_like(o[:, 0], torch.inf), steps=p.steps, refine=True)
        color = background.clone()
        aovs = {k: o.new_zeros(n, 3) for k in self.aov_names}
        ids = hit.nonzero().squeeze(1)
        if ids.numel():
            at = lambda x: take_rows(x, ids)  # noqa: E731  (index_select: 3× faster than x[ids])
            sh, th = at(s), at(t)
            with section("terrain.shade"):
                x = at(o) + th[:, None] * at(d)
                inside = self._kernel_occluders(sh)
                shade = self._shade if inside is None else partial(self._shade_kernel, inside=inside)
                rgb, nrm = shade(x, th, sh, section)
            color.index_copy_(0, ids, rgb)
            for k in self.aov_names:
                aovs[k].index_copy_(0, ids, nrm)
        return SurfaceHit(hit=hit, t=torch.where(hit, t, torch.full_like(t, torch.inf)), color=color, aovs=aovs)

    def _uses(self) -> dict:
        """The sky's visibility ray (key None) and each shadowed light's shadow ray (key: its
        index): their LightPasses."""
        return {**({None: self.plan.sky} if self.plan.sky is not None else {}),
                **{use.light: use for use in self.plan.shadows}}

    def _kernel_occluders(self, sh: Tensor) -> dict | None:
        """Each of `_uses`' occluder lanes for hits of scenes `sh` [m], or None: shading eagerly
        (no kernels, or one of them cannot be seen from a kernel)."""
        if not self.kernels or self.occluder_lanes is None:
            return None
        return self.occluder_lanes(self._uses(), sh)

    def _shade(self, x: Tensor, th: Tensor, sh: Tensor, section) -> tuple[Tensor, Tensor]:
        """(colour, normal) [m, 3] of hits x [m, 3] at distances th [m] of scenes sh [m]: `_colour`
        on torch columns, the sky and shadow rays through `transmittance`, each its own pass."""
        p, uses = self.p, self._uses()
        nrm = normal_kernel(p, x, sh) if self.kernels else normal(p, x, sh)
        look = _look(p, lambda v: lanes.columns(take(v, sh)))
        start = torch.stack(look.lift(x.unbind(1), nrm.unbind(1), th), dim=1)
        sky = None
        if None in uses:  # the sky light's visibility: straight up through the volumes
            with section(uses[None].name):
                up = torch.zeros_like(start)
                up[:, 1] = 1.0
                sky = self.transmittance(uses[None], start, sh, up, torch.full_like(th, torch.inf))
        lights = []
        for l, source in enumerate(self.lights):
            toward = source.toward(x, sh)
            visible = lambda lit: lit  # noqa: E731
            if l in uses:
                def visible(lit, use=uses[l], toward=toward):
                    with section(use.name):
                        return self.transmittance(use, start, sh, toward.direction, toward.distance, lit)
            lights.append((toward.direction.unbind(1), toward.irradiance.unbind(1), visible))
        return torch.stack(_colour(look, nrm.unbind(1), lanes.columns(take(p.ambient, sh)), sky, lights), dim=1), nrm

    def _shade_kernel(self, x: Tensor, th: Tensor, sh: Tensor, section, *, inside: dict) -> tuple[Tensor, Tensor]:
        """`_shade` as one Dr.Jit kernel: the normal, look, the sky's and each light's rays
        (`inside`: their occluder lanes, by `_uses`' key) and `_colour`; their passes listed in
        `stats`, their time the shading's. A shadow ray is traced only where n·l > 0, as eager's."""
        import drjit as dr

        p, uses = self.p, self._uses()
        q, columns, per_scene = _kernel_lanes(p, sh)
        xl = columns(x)
        nrm = normal_lanes(q, xl[0], xl[2])
        look = _look(p, per_scene)
        start = look.lift(xl, nrm, columns(th))
        sky = None
        if None in uses:
            up = torch.zeros_like(x)
            up[:, 1] = 1.0
            sky = inside[None].through(start, columns(up), torch.full_like(th, torch.inf))
        lights = []
        for l, source in enumerate(self.lights):
            toward = source.toward(x, sh)
            direction = columns(toward.direction)
            visible = lambda lit: lit  # noqa: E731
            if l in uses:
                def visible(lit, k=inside[l], direction=direction, distance=toward.distance):
                    lit_here = lit > 0.0
                    return dr.select(lit_here, k.through(start, direction, distance, lit_here) * lit, lit)
            lights.append((direction, columns(toward.irradiance), visible))
        rgb, nrm = lanes.interleaved(_colour(look, nrm, per_scene(p.ambient), sky, lights)), lanes.interleaved(nrm)
        dr.eval(rgb, nrm, [e for k in inside.values() for e in k.evals()])
        dr.sync_thread()
        for key, use in uses.items():
            inside[key].count()
            for name in use.names():
                with section(name):
                    pass
        return lanes.rows_of(rgb, 3).to(x), lanes.rows_of(nrm, 3).to(x)


__all__ = ["Terrain", "TerrainSurface", "gap", "height", "normal", "normal_kernel", "path_surface", "trace", "trace_kernel", "visibility"]
