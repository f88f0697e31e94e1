"""The atmosphere (seed 000, variant 2): a planet-scale spherical shell of exponential Rayleigh and
Mie densities, each with its own scale height, single scattering of the sun with the seeds' nested
optical-depth march towards it. One function, `single_scatter`, serves both the `atmosphere` sky
(`torchvol.light.sky`: the shell seen from a fixed height, as a background) and the top-level
`[atmosphere]` medium (`AirPath`: the scene inside the shell, whose ground y = 0 is the
planet's surface, centre (0, −R, 0), with the camera anywhere: on the ground, in the air, in space).

The medium is one of the media of the camera rays' march (`AirPath`, marched with the volumes by
`volume.joint`): every sample's light reaches the camera through the air in front of it, the
air's in-scatter is summed in every piece of the ray inside the shell, and behind everything lie
the planet's ground (Lambertian, lit by the sun through the air, opaque) or space. The sun that
reaches any point of the scene (a volume's sample, a voxel face, the terrain) comes through the
air (`sun_transmittance`, the lights' `through`).

Lengths are world units (the defaults are Earth's in metres); coefficients are per world unit at
the ground. Mie extinction is 1.1 × its scattering (the seeds' aerosol absorption).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from types import SimpleNamespace
from typing import Literal

import torch
from pydantic import Field, field_validator
from torch import Tensor

from ..geometry.rays import sphere_interval
from ..ops import lanes
from ..ops.mathops import take_rows
from ..runtime.compilation import traced, traced_vectors
from ..runtime.threads import set_drjit_threads
from ..schema.batch import Stacked, take
from ..schema.models import Strict, Vec3, nonneg
from .phase import mie_cornette_shanks
from .phase import rayleigh as rayleigh_phase

MIE_EXTINCTION = 1.1  # Mie extinction / Mie scattering


class AirLayer(Strict):
    """The shell and its air, shared by the `atmosphere` sky and the `[atmosphere]` medium."""

    planet_radius: float = Field(6.36e6, gt=0.0)
    atmosphere_height: float = Field(6.0e4, gt=0.0)
    rayleigh: Vec3 = (5.8e-6, 13.5e-6, 33.1e-6)
    mie: float = Field(21e-6, ge=0.0)
    rayleigh_height: float = Field(7994.0, gt=0.0)
    mie_height: float = Field(1200.0, gt=0.0)
    mie_g: float = Field(0.76, gt=-1.0, lt=1.0)
    steps: int | None = Field(None, ge=1, le=1024, description="None: the quality level's")
    light_steps: int | None = Field(None, ge=1, le=1024, description="None: the quality level's")
    sun_depth: Literal["march", "table"] = Field(
        "march", description="the optical depth towards the sun: the seeds' nested march of light_steps at every "
        "sample, or looked up in a table over (height, sun angle) whose nodes are marched so (`sun_depth_table`)")
    _r = field_validator("rayleigh")(lambda v: nonneg(v))


class AtmosphereMedium(AirLayer):
    """The top-level `[atmosphere]`: the scene inside the shell (ground y = 0, planet centre
    (0, −planet_radius, 0)), lit by lights[0], a sun; `ground` is the planet surface's albedo."""

    ground: Vec3 = (0.3, 0.3, 0.3)
    _g = field_validator("ground")(lambda v: nonneg(v))


@dataclass(frozen=True)
class Air:
    """An `AirLayer` gathered per ray: radii, scale heights, `mie`, `mie_g` [n]; `rayleigh` [n, 3];
    with a sun-depth table (`sun_depth_table`, the batch's: not gathered; None: the nested march)
    each ray's scene's first node `table_base` [n] (int32) and `horizon` [n] (√(top² − R²))."""

    planet_radius: Tensor
    top_radius: Tensor
    rayleigh: Tensor
    mie: Tensor
    scale_heights: Tensor  # [n, 2]: Rayleigh's, Mie's
    mie_g: Tensor
    table: Tensor | None = None
    table_base: Tensor | None = None
    horizon: Tensor | None = None


def gather_air(layer: Stacked, s: Tensor, *, kernel: bool = False) -> Air:
    """The layer's values (B, ...) at the scenes `s` [n] of the rays; its sun-depth table
    (`sun_depth_table`) built as a Dr.Jit kernel where `kernel` (the caller's lanes run in one)."""
    air = Air(planet_radius=take(layer.planet_radius, s), top_radius=take(layer.planet_radius + layer.atmosphere_height, s),
              rayleigh=take(layer.rayleigh, s), mie=take(layer.mie, s), mie_g=take(layer.mie_g, s),
              scale_heights=take(torch.stack([layer.rayleigh_height, layer.mie_height], dim=1), s))
    table = sun_depth_table(layer, kernel=kernel)
    if table is None:
        return air
    return replace(air, table=table, table_base=(s * (TABLE_HEIGHTS * TABLE_ANGLES)).to(torch.int32),
                   horizon=take(_horizon(layer.planet_radius, layer.planet_radius + layer.atmosphere_height), s))


def air_lanes(air: Air, lane=lambda x: x) -> SimpleNamespace:
    """An `Air` as the lanes functions take it (`ops.lanes`): one lane a value (`lane`: a tensor
    [n] -> lanes; the columns themselves for the eager code), `rayleigh` three, `falloff` two
    (`falloff_rates` of Rayleigh's and Mie's scale heights); its sun-depth `table` as
    `table_depth_lanes` reads it (None: none)."""
    q = SimpleNamespace(planet_radius=lane(air.planet_radius), top_radius=lane(air.top_radius),
                        rayleigh=[lane(x) for x in air.rayleigh.unbind(1)], mie=lane(air.mie),
                        falloff=[lane(x) for x in falloff_rates(air.scale_heights).unbind(-1)], mie_g=lane(air.mie_g),
                        table=None)
    if air.table is not None:
        kernel = not isinstance(q.planet_radius, Tensor)
        q.table = lanes.pairs_of(air.table) if kernel else air.table
        q.table_base = lanes.ints_of(air.table_base) if kernel else air.table_base
        q.horizon = lane(air.horizon)
    return q


def falloff_rates(scale_heights: Tensor) -> Tensor:
    """1/H of scale heights H (any shape): `density_lanes` multiplies by them once per ray where
    dividing by H cost two divisions an evaluation (most of the air's nested march)."""
    return 1.0 / scale_heights


def density_lanes(p, q: SimpleNamespace) -> list:
    """The seeds' `density(p, H) = exp(−max(|p| − R, 0) / H)` at `p` (three lanes, planet frame)
    for both scale heights of `q` (`air_lanes`; as their `falloff` rates 1/H) -> two lanes
    (Rayleigh, Mie). The height as
    (|p|² − R²)/(|p| + R), |p|² − R² = x² + z² + (y − R)(y + R): |p| − R cancels to an ulp of R
    (0.5 m at Earth's radius in float32, 4e-4 of Mie's scale height), and Dr.Jit's sqrt rounds
    that ulp otherwise than torch's; the quotient leaves |p| in the denominator alone."""
    r = q.planet_radius
    excess = p[0] * p[0] + p[2] * p[2] + (p[1] - r) * (p[1] + r)
    height = lanes.clamp_min(excess / (lanes.length3(*p) + r), 0.0)
    return [lanes.exp(-(height * rate)) for rate in q.falloff]


def optic_depth_lanes(start, direction, length, q: SimpleNamespace, steps: int) -> list:
    """The seeds' `opticDepth(from, to)`: ∫ density from `start` along unit `direction` (three lanes
    each, planet frame) for `length` (a lane), the midpoint rule with `steps` steps -> two lanes
    (Rayleigh, Mie) in density × length."""
    ds = lanes.divide(length, steps)

    def step(j, depth):
        density = density_lanes([start[c] + ((j + 0.5) * ds) * direction[c] for c in range(3)], q)
        return [depth[k] + density[k] * ds for k in range(2)]

    return lanes.fori(steps, [lanes.full_like(length, 0.0)] * 2, step)


def extinction_lanes(depth, q: SimpleNamespace) -> list:
    """Optical thickness per colour (three lanes) of optic depths `depth` (two lanes: Rayleigh, Mie)."""
    mie = MIE_EXTINCTION * q.mie * depth[1]
    return [q.rayleigh[c] * depth[0] + mie for c in range(3)]


def sun_depth_lanes(p, sun_dir, length, q: SimpleNamespace, light_steps: int) -> list:
    """Optic depths (two lanes: Rayleigh, Mie) from `p` towards the sun `sun_dir` (three lanes
    each, planet frame; unit) over `length` (a lane, `sun_path_lanes`' distance to the top): the
    seeds' nested march of `light_steps` (`optic_depth_lanes`), or looked up in `q`'s table."""
    if q.table is None:
        return optic_depth_lanes(p, sun_dir, length, q, light_steps)
    return table_depth_lanes(p, length, q)


# the sun-depth table's nodes: heights × sun angles, in Bruneton's parameterisation (2017,
# "Precomputed Atmospheric Scattering: a New Implementation"): the height by ρ = √(r² − R²) / H,
# the angle by where the distance to the top lies between its least and most at that height
TABLE_HEIGHTS, TABLE_ANGLES = 64, 256


def _horizon(planet_radius: Tensor, top_radius: Tensor) -> Tensor:
    """H = √(top² − R²): the distance to the top along the ground's horizon."""
    return ((top_radius - planet_radius) * (top_radius + planet_radius)).sqrt()


def sun_depth_table(layer: Stacked, *, kernel: bool = False) -> Tensor | None:
    """The optical depths towards the sun of each scene of `layer` (an `AirLayer` batch of B
    scenes; None where its `sun_depth` is "march") at `TABLE_HEIGHTS` × `TABLE_ANGLES` nodes, as
    their logarithms (linear between nodes is exponential in height, as the air is) ->
    [B·heights·angles, 2] (Rayleigh, Mie; height-major), built once a batch: each node the nested
    march of `light_steps` (`optic_depth_lanes`) from its point and direction in float64, marched
    in float64 on torch, or where `kernel` in one Dr.Jit kernel (float32, as the kernels march)."""
    if layer.sun_depth != "table":
        return None
    key = "sun_table_kernel" if kernel else "sun_table"
    if key not in layer.__dict__:  # (Stacked keeps what it computes for the batch there)
        wide = lambda x: x.to(torch.float64)[:, None, None]  # noqa: E731  (B, 1, 1)
        radius, top = wide(layer.planet_radius), wide(layer.planet_radius + layer.atmosphere_height)
        h = _horizon(radius, top)
        u_r = torch.linspace(0.0, 1.0, TABLE_HEIGHTS, dtype=torch.float64)[:, None]
        u_mu = torch.linspace(0.0, 1.0, TABLE_ANGLES, dtype=torch.float64)
        rho = h * u_r
        r = (rho * rho + radius * radius).sqrt()
        d_min, d_max = top - r, rho + h
        d = d_min + u_mu * (d_max - d_min)  # (B, heights, angles)
        mu = torch.where(d > 0, (h * h - rho * rho - d * d) / (2.0 * r * d.clamp_min(1e-30)), 1.0).clamp(-1.0, 1.0)
        dtype = torch.float32 if kernel else torch.float64
        node = lambda x: x.expand_as(d).reshape(-1).to(dtype).contiguous()  # noqa: E731
        columns = [node(radius), node(falloff_rates(wide(layer.rayleigh_height))), node(falloff_rates(wide(layer.mie_height))),
                   node(r), node((1.0 - mu * mu).clamp_min(0.0).sqrt()), node(mu), node(d)]

        def march(lane):
            radius, rayleigh, mie, r, across, up, length = (lane(c) for c in columns)
            zero = up * 0.0
            q = SimpleNamespace(planet_radius=radius, falloff=[rayleigh, mie])
            return optic_depth_lanes([zero, r, zero], [across, up, zero], length, q, int(layer.light_steps))

        depth = traced(march, columns[0]) if kernel else march(lambda x: x)
        layer.__dict__[key] = (torch.stack(depth, dim=1).double() + 1e-30).log().to(layer.planet_radius.dtype)
    return layer.__dict__[key]


def table_depth_lanes(p, length, q: SimpleNamespace) -> list:
    """`sun_depth_table`'s optical depths (two lanes) at `p` (three lanes, planet frame) towards a
    sun whose path to the top is `length` (a lane; 0: none, nothing to cross), their logarithms
    bilinear between its nodes; a point above the top takes the top's. ρ² = |p|² − R² as
    `density_lanes` writes it."""
    r = q.planet_radius
    rho = lanes.sqrt(lanes.clamp_min(p[0] * p[0] + p[2] * p[2] + (p[1] - r) * (p[1] + r), 0.0))
    d_min, d_max = q.top_radius - lanes.length3(*p), rho + q.horizon
    x = lanes.clamp((length - d_min) / (d_max - d_min), 0.0, 1.0) * float(TABLE_ANGLES - 1)
    y = lanes.clamp(rho / q.horizon, 0.0, 1.0) * float(TABLE_HEIGHTS - 1)
    x0, y0 = lanes.minimum(lanes.floor(x), float(TABLE_ANGLES - 2)), lanes.minimum(lanes.floor(y), float(TABLE_HEIGHTS - 2))
    fx, fy = x - x0, y - y0
    first = q.table_base + lanes.to_int32(y0) * TABLE_ANGLES + lanes.to_int32(x0)
    a, b = lanes.gather_pair(q.table, first), lanes.gather_pair(q.table, first + 1)
    c, e = lanes.gather_pair(q.table, first + TABLE_ANGLES), lanes.gather_pair(q.table, first + TABLE_ANGLES + 1)
    return [lanes.where(length > 0, lanes.exp(lanes.lerp(lanes.lerp(a[k], b[k], fx), lanes.lerp(c[k], e[k], fx), fy)), 0.0)
            for k in range(2)]


def sun_path_lanes(p, sun_dir, q: SimpleNamespace):
    """From `p` towards the sun `sun_dir` (three lanes each, planet frame; unit): the distance to
    the top of the atmosphere (0 outside it, going away) and whether the planet blocks the sun."""
    centre = (0.0, 0.0, 0.0)
    _, top = sphere_interval(p, sun_dir, centre, q.top_radius)
    near, far = sphere_interval(p, sun_dir, centre, q.planet_radius)
    return lanes.clamp_min(top, 0.0), (near > 0) & (near <= far)  # a miss is (inf, -inf): not in the way


def sun_transmittance_lanes(p, sun_dir, q: SimpleNamespace, light_steps: int) -> list:
    """The air's transmittance (three lanes) from `p` to the sun `sun_dir` (three lanes each, planet
    frame; unit): the nested optical-depth march, 0 where the planet is in the way."""
    length, blocked = sun_path_lanes(p, sun_dir, q)
    tau = extinction_lanes(sun_depth_lanes(p, sun_dir, length, q, light_steps), q)
    return [lanes.where(blocked, 0.0, lanes.exp(-x)) for x in tau]


def scattering_lanes(density, cos, q: SimpleNamespace) -> list:
    """σ_s·p(θ) per colour (three lanes) of the air at densities `density` (two lanes) for the
    cosine `cos` between the view ray and the sun: Rayleigh's and Mie's (Cornette-Shanks) summed."""
    rayleigh = density[0] * rayleigh_phase(cos)
    mie = density[1] * (q.mie * mie_cornette_shanks(cos, q.mie_g))
    return [rayleigh * q.rayleigh[c] + mie for c in range(3)]


def air_source_lanes(p, direction, sun_dir, sun, q: SimpleNamespace, light_steps: int) -> list:
    """The sun's light scattered by the air towards the camera per unit length (three lanes) at `p`
    (planet frame) of a ray along `direction`, the sun `sun_dir` (unit) of irradiance `sun` (three
    lanes each): σ_s·p(θ)·E·T_sun."""
    cos = lanes.dot3(direction, sun_dir)
    scatter = scattering_lanes(density_lanes(p, q), cos, q)
    trans = sun_transmittance_lanes(p, sun_dir, q, light_steps)
    return [sun[c] * trans[c] * scatter[c] for c in range(3)]


def depth_transmittance_lanes(t, enter, span, nodes: int, fetch) -> list:
    """exp(−τ) at distance `t` along a ray whose optical depth is tabulated at `nodes` + 1 even
    nodes over [enter, enter + span] (lanes; span > 0), linearly between them: `fetch(i)` gives
    node i's τ (three lanes) for int32 lanes i."""
    u = lanes.clamp((t - enter) / span, 0.0, 1.0) * nodes
    lo = lanes.minimum(lanes.floor(u), float(nodes - 1))
    index = lanes.to_int32(lo)
    a, b = fetch(index), fetch(index + 1)
    return [lanes.exp(-lanes.lerp(a[c], b[c], u - lo)) for c in range(3)]


def _columns(x: list) -> Tensor:
    return torch.stack(x, dim=1)


def optic_depth(start: Tensor, direction: Tensor, length: Tensor, air: Air, steps: int) -> Tensor:
    """`optic_depth_lanes` from `start` [n, 3] (planet frame) along unit `direction` [n, 3] for
    `length` [n] -> [n, 2] (Rayleigh, Mie)."""
    return _columns(optic_depth_lanes(start.unbind(1), direction.unbind(1), length, air_lanes(air), steps))


def sun_path(points: Tensor, sun_dir: Tensor, air: Air) -> tuple[Tensor, Tensor]:
    """`sun_path_lanes` of `points`, `sun_dir` [n, 3] -> (distance [n], blocked [n])."""
    return sun_path_lanes(points.unbind(1), sun_dir.unbind(1), air_lanes(air))


def single_scatter_lanes(origins, directions, t0, t1, sun_dir, q: SimpleNamespace, *, steps: int,
                         light_steps: int) -> tuple[list, list]:
    """`single_scatter` in lanes (`ops.lanes`): `origins`, `directions`, `sun_dir` three lanes each
    (planet frame; unit directions), `t0`, `t1` lanes, the air `q` (`air_lanes`). -> (in-scatter,
    transmittance), three lanes each."""
    dt = lanes.divide(lanes.clamp_min(t1 - t0, 0.0), steps)
    d, sun = directions, sun_dir
    cos = lanes.dot3(d, sun)

    def sample(i, state):  # state: the optical depth so far (2), Rayleigh's and Mie's attenuated sums (3 each)
        optical, sums = state[:2], [state[2:5], state[5:8]]
        t = t0 + (i + 0.5) * dt
        p = [origins[c] + t * d[c] for c in range(3)]
        step = [x * dt for x in density_lanes(p, q)]
        optical = [optical[k] + step[k] for k in range(2)]
        length, blocked = sun_path_lanes(p, sun, q)
        toward = sun_depth_lanes(p, sun, length, q, light_steps)
        tau = extinction_lanes([optical[k] + toward[k] for k in range(2)], q)
        attenuation = [lanes.where(blocked, 0.0, lanes.exp(-x)) for x in tau]
        return optical + [sums[k][c] + attenuation[c] * step[k] for k in range(2) for c in range(3)]

    state = lanes.fori(steps, [lanes.full_like(dt, 0.0)] * 8, sample)
    optical, sums = state[:2], [state[2:5], state[5:8]]
    rayleigh, mie = rayleigh_phase(cos), q.mie * mie_cornette_shanks(cos, q.mie_g)
    inscatter = [sums[0][c] * q.rayleigh[c] * rayleigh + sums[1][c] * mie for c in range(3)]
    return inscatter, [lanes.exp(-x) for x in extinction_lanes(optical, q)]


def single_scatter(origins: Tensor, directions: Tensor, t0: Tensor, t1: Tensor, sun_dir: Tensor, air: Air, *,
                   steps: int, light_steps: int) -> tuple[Tensor, Tensor]:
    """Single scattering of the sun by the air on the segment [t0, t1] [n] of rays `origins`,
    `directions` [n, 3] (planet frame, unit directions), `steps` midpoint samples, each with
    `light_steps` towards the sun `sun_dir` [n, 3] (unit). -> (in-scatter [n, 3] per unit sun
    irradiance, seen from t0; transmittance [n, 3] from t0 to t1). t1 ≤ t0 gives (0, 1)."""
    inscatter, trans = single_scatter_lanes(origins.unbind(1), directions.unbind(1), t0, t1, sun_dir.unbind(1),
                                            air_lanes(air), steps=steps, light_steps=light_steps)
    return _columns(inscatter), _columns(trans)


def single_scatter_kernel(origins: Tensor, directions: Tensor, t0: Tensor, t1: Tensor, sun_dir: Tensor, air: Air, *,
                          steps: int, light_steps: int) -> Tensor:
    """`single_scatter`'s in-scatter [n, 3] as one Dr.Jit kernel over the rays (float32 on the CPU;
    the same lanes function, traced): the atmosphere sky's per-pixel march."""
    import drjit as dr

    set_drjit_threads()
    cols = lambda x: [lanes.floats_of(c) for c in x.unbind(1)]  # noqa: E731
    inscatter, _ = single_scatter_lanes(cols(origins), cols(directions), lanes.floats_of(t0), lanes.floats_of(t1),
                                        cols(sun_dir), air_lanes(air, lanes.floats_of), steps=steps,
                                        light_steps=light_steps)
    rows = lanes.interleaved(inscatter)
    dr.eval(rows)
    return lanes.rows_of(rows, 3).to(origins)


def _segments(mask: Tensor, origins: Tensor, directions: Tensor, t0: Tensor, t1: Tensor, sun_dir: Tensor, air: Air,
              steps: int, light_steps: int) -> tuple[Tensor, Tensor]:
    """`single_scatter` of the rays where `mask` [n]; the others get an empty segment's (0, 1)."""
    inscatter, trans = torch.zeros_like(origins), torch.ones_like(origins)
    rays = mask.nonzero().squeeze(1)
    if rays.numel():
        part = rows_of(air, rays)
        inscatter[rays], trans[rays] = single_scatter(origins[rays], directions[rays], t0[rays], t1[rays], sun_dir[rays],
                                                      part, steps=steps, light_steps=light_steps)
    return inscatter, trans


def planet_frame(origins: Tensor, air: Air) -> Tensor:
    """World points [n, 3] (ground y = 0) -> relative to the planet's centre (0, −R, 0)."""
    return origins + torch.stack([torch.zeros_like(air.planet_radius), air.planet_radius,
                                  torch.zeros_like(air.planet_radius)], dim=1)


def ground_distance_lanes(o, d, planet_radius):
    """Distance along world rays `o`, `d` (three lanes each, d unit) to the planet's surface in
    front of them (radius `planet_radius`, centre (0, −R, 0)); inf where they miss it or start
    below it, lanes (`ops.lanes`). The ray/sphere roots with c = |o − centre|² − R² written
    |o|² + 2R·y: no cancellation near the ground (the sphere test in the planet's frame, R² ≈ 4e13
    in float32, puts a camera 2 m up at 1.5–2.5 m)."""
    c = (o[0] * o[0] + o[1] * o[1] + o[2] * o[2]) + 2.0 * planet_radius * o[1]
    b = (o[0] * d[0] + o[1] * d[1] + o[2] * d[2]) + planet_radius * d[1]
    disc = b * b - c
    hit = (c > 0) & (b < 0) & (disc >= 0)  # above the ground, heading down, meeting the sphere
    q = lanes.where(hit, lanes.sqrt(lanes.clamp_min(disc, 0.0)) - b, 1.0)  # −b + √disc > 0: no cancellation
    return lanes.where(hit, c / q, math.inf)


def ground_distance(origins: Tensor, directions: Tensor, planet_radius: Tensor) -> Tensor:
    """`ground_distance_lanes` of world rays `origins`, `directions` [n, 3] (unit), the planet's
    radius `planet_radius` [n] -> [n]."""
    return ground_distance_lanes(origins.unbind(1), directions.unbind(1), planet_radius)


def shell_span(origins: Tensor, directions: Tensor, air: Air, *, kernel: bool = False) -> tuple[Tensor, Tensor, Tensor]:
    """Where world rays `origins`, `directions` [n, 3] (unit) are in the air: (enter, leave [n]:
    both 0 for a ray that misses the shell; leave is the ground where the ray meets it first,
    ground [n]: the distance to the planet's surface, inf where the ray does not reach it).
    `kernel`: as one Dr.Jit kernel (its sqrt correctly rounded: within an ulp of eager's)."""
    if kernel:
        return tuple(traced(lambda lane: shell_span_lanes(lanes.vector_lanes(origins), lanes.vector_lanes(directions),
                                                          lane(air.planet_radius), lane(air.top_radius)), origins))
    return shell_span_lanes(origins.unbind(1), directions.unbind(1), air.planet_radius, air.top_radius)


def shell_span_lanes(o, d, planet_radius, top_radius) -> tuple:
    """`shell_span` in lanes (`ops.lanes`): world rays o, d (three lanes each), the radii one lane
    each -> (enter, leave, ground)."""
    p = [o[0] + 0.0, o[1] + planet_radius, o[2] + 0.0]  # the planet's frame (`planet_frame`'s sums)
    top_near, top_far = sphere_interval(p, d, (0.0, 0.0, 0.0), top_radius)
    inside = top_far > 0  # a miss is (inf, -inf)
    enter = lanes.where(inside, lanes.clamp_min(top_near, 0.0), 0.0)
    leave = lanes.where(inside, top_far, 0.0)
    g_near = ground_distance_lanes(o, d, planet_radius)
    ground = lanes.where(inside & (g_near < leave), g_near, math.inf)
    return enter, lanes.minimum(leave, ground), ground


def sun_transmittance(points: Tensor, sun_dir: Tensor, air: Air, light_steps: int, *, kernel: bool = False) -> Tensor:
    """`sun_transmittance_lanes` of `points`, `sun_dir` [n, 3] (planet frame; unit) -> [n, 3];
    `kernel`: as one Dr.Jit kernel (float32 on the CPU), else eagerly."""
    if kernel:
        return traced_vectors(lambda lane: sun_transmittance_lanes(lanes.vector_lanes(points), lanes.vector_lanes(sun_dir),
                                                                   air_lanes(air, lane), light_steps), points)
    return _columns(sun_transmittance_lanes(points.unbind(1), sun_dir.unbind(1), air_lanes(air), light_steps))


def ground_radiance(points: Tensor, sun_dir: Tensor, sun: Tensor, albedo: Tensor, air: Air, light_steps: int, *,
                    kernel: bool = False) -> Tensor:
    """The planet's ground at `points` [n, 3] (planet frame, on the surface): Lambertian of `albedo`
    [n, 3], lit by the sun (`sun_dir` [n, 3], irradiance `sun` [n, 3]) through the air (its march
    towards the sun a Dr.Jit kernel where `kernel`). -> [n, 3]."""
    normal = points / points.norm(dim=1, keepdim=True)
    cos = (normal * sun_dir).sum(dim=1).clamp_min(0.0)
    return albedo / math.pi * sun * sun_transmittance(points, sun_dir, air, light_steps, kernel=kernel) * cos[:, None]


def rows_of(air: Air, rows: Tensor) -> Air:
    """The rays `rows` [m] of `air` (gathered per ray; its table is the batch's)."""
    return Air(**{f.name: getattr(air, f.name) if f.name == "table" or getattr(air, f.name) is None
                  else take_rows(getattr(air, f.name), rows) for f in fields(air)})


@dataclass(frozen=True)
class AirPath:
    """The air along a chunk's camera rays, as a medium of their march (`volume.joint`): `origins`
    (planet frame), `directions` [n, 3]; `enter`, `leave`, `ground` [n] (`shell_span`); the optical
    depth from the camera at `nodes` + 1 even nodes over [enter, leave]: `tables`, three Dr.Jit
    arrays [(nodes + 1)·n] where a kernel built it (node i of ray r at i·n + r: a vector of rays
    reads a node's consecutive values; the march kernel reads them as they are), else `depth`
    [3, n, nodes + 1]; the sun's direction and irradiance [n, 3]; the air [n] and its `light_steps`."""

    origins: Tensor
    directions: Tensor
    enter: Tensor
    leave: Tensor
    ground: Tensor
    nodes: int
    depth: Tensor | None
    tables: list | None
    sun_dir: Tensor
    sun: Tensor
    air: Air
    light_steps: int

    def transmittance(self, rows: Tensor, t: Tensor) -> Tensor:
        """The air's transmittance [m, 3] from the camera to distance `t` [m] along rays `rows` [m]
        (`depth_transmittance_lanes`: the table interpolated linearly, exact where the air is
        homogeneous); a Dr.Jit kernel where its `tables` are Dr.Jit's."""
        enter = self.enter.index_select(0, rows)
        span = (self.leave.index_select(0, rows) - enter).clamp_min(torch.finfo(t.dtype).tiny)
        if self.tables is not None:
            fetch = self.fetch(lanes.ints_of(rows))
            return traced_vectors(lambda lane: depth_transmittance_lanes(lane(t), lane(enter), lane(span), self.nodes, fetch), t)
        tables = [c.index_select(0, rows) for c in self.depth]  # 3 × [m, K + 1]
        fetch = lambda i: [table.gather(1, i.long()[:, None])[:, 0] for table in tables]  # noqa: E731
        return _columns(depth_transmittance_lanes(t, enter, span, self.nodes, fetch))

    def fetch(self, rows):
        """`depth_transmittance_lanes`' fetch from the kernel's `tables`: node i (int32 lanes) of
        rays `rows` (int32 lanes) -> three lanes."""
        import drjit as dr
        from drjit.llvm import Float

        n = self.enter.shape[0]
        return lambda i: [dr.gather(Float, table, i * n + rows) for table in self.tables]

    def source(self, rows: Tensor, t: Tensor) -> Tensor:
        """The sun's light scattered by the air towards the camera per unit length [m, 3] at
        distance `t` [m] along rays `rows` [m] (not yet attenuated on the way to the camera)."""
        d = self.directions[rows]
        p = self.origins[rows] + t[:, None] * d
        return _columns(air_source_lanes(p.unbind(1), d.unbind(1), self.sun_dir[rows].unbind(1),
                                         self.sun[rows].unbind(1), air_lanes(rows_of(self.air, rows)), self.light_steps))


def depth_table_lanes(o, d, enter, dt, q: SimpleNamespace, steps: int) -> list:
    """The optical depth (three lanes) from `enter` at `steps` + 1 even nodes `dt` apart along rays
    `o`, `d` (three lanes each, planet frame; `enter`, `dt` lanes; `q` from `air_lanes`), each
    step's by the midpoint rule -> [node][colour] lanes, node 0 zero."""
    depth = [[lanes.full_like(dt, 0.0)] * 3]
    for i in range(steps):
        t = enter + (i + 0.5) * dt
        density = density_lanes([o[c] + t * d[c] for c in range(3)], q)
        tau = extinction_lanes([x * dt for x in density], q)
        depth.append([depth[-1][c] + tau[c] for c in range(3)])
    return depth


def air_path(origins: Tensor, directions: Tensor, sun_dir: Tensor, sun: Tensor, air: Air, *, steps: int,
             light_steps: int, kernel: bool = False) -> AirPath:
    """The `AirPath` of world rays `origins`, `directions` [n, 3] lit by the sun `sun_dir` [n, 3]
    (irradiance `sun` [n, 3]): the optical depth tabulated at `steps` + 1 nodes (`depth_table_lanes`),
    `light_steps` for the march towards the sun. `kernel`: the table as one Dr.Jit kernel (float32
    on the CPU: the joint march's kernel reads it), else eagerly."""
    o = planet_frame(origins, air)
    enter, leave, ground = shell_span(origins, directions, air, kernel=kernel)
    dt = (leave - enter).clamp_min(0.0) / steps
    depth = tables = None
    if kernel:
        tables = _depth_table_kernel(o, directions, enter, dt, air, steps)
    else:
        nodes = depth_table_lanes(o.unbind(1), directions.unbind(1), enter, dt, air_lanes(air), steps)
        depth = torch.stack([torch.stack([node[c] for node in nodes], dim=1) for c in range(3)])
    return AirPath(o, directions, enter, leave, ground, steps, depth, tables, sun_dir, sun, air, light_steps)


def _depth_table_kernel(o: Tensor, d: Tensor, enter: Tensor, dt: Tensor, air: Air, steps: int) -> list:
    """`depth_table_lanes` of rays `o`, `d` [n, 3] (`enter`, `dt` [n]) as one Dr.Jit kernel -> three
    Dr.Jit arrays [(K + 1)·n], node-major (`AirPath.tables`), never copied into torch."""
    import drjit as dr

    set_drjit_threads()
    lane = lanes.floats_of
    nodes = depth_table_lanes([lane(c) for c in o.unbind(1)], [lane(c) for c in d.unbind(1)], lane(enter), lane(dt),
                              air_lanes(air, lane), steps)
    dr.eval(nodes)
    tables = [dr.concat([node[c] for node in nodes]) for c in range(3)]
    dr.eval(tables)
    return tables
