"""The voxels as the path tracer's opaque surface (`volume.path`, `[path]`).

A path meets the voxels where the DDA walk (`walk.walk_step`, the same step, tie rule and
distance-field jump as every other walk) first finds an occupied cell; the face it entered by
gives the normal (`shade.face_lanes`: −sign(d) on the entry axis), the cell's material its
reflectance (Lambert of its `color` times the face's texel where the scene has a `texture`:
`shade.texel_lanes`; or GGX: `ggx.reflectance_lanes`, `ggx_bounce`) and the light its faces emit
(`emission`). Shadow rays are the same walk,
up to the light. Written once in lanes: torch columns for the eager tracer, Dr.Jit arrays inside
the path kernel (`volume.path_kernel`), a loop nested in the path's loop.

Under `[path]` the marched look's stand-ins are dropped (`scene.quality.at_level`): `ambient`,
`ao`, `gi`, the mirror `reflections` and the face tones; what a path cannot trace yet is refused
by the schema (glow, the voxel fog, water). Rounded voxels (`voxels.rounded`) are their rounded
boxes, for hits and shadow rays alike (`walk.rounded_walk`, the marched voxels' walk too).
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import torch
from torch import Tensor

from ..geometry.scatter import basis, facing, turn
from ..ops import lanes
from ..schema.batch import Stacked
from .ggx import alpha_of, d_ggx, reflectance_lanes, sin2_between
from .grid import VoxelGrid
from .materials import material_lanes, material_table
from .shade import atlas_lanes, atlas_table, face_lanes, face_uv_lanes
from .walk import cube_walk, rounded_walk, walk_inputs

__all__ = ["path_surface"]

LIFT = 1e-4  # a bounce or shadow ray leaves a face this many voxels (plus as much of its distance) off it


def path_surface(voxels: Stacked, grid: VoxelGrid, s: Tensor, per_lane, like: Tensor, *, kernel: bool) -> SimpleNamespace:
    """The voxel grids of scenes `s` [n] as the path tracer's surface, lanes (`per_lane`: per scene
    -> lanes; `kernel`: Dr.Jit arrays, else torch columns like `like`): `hit(o, d, t_max)` -> (the
    first occupied cell's entry t (inf: none), its facts: the face's normal (three lanes) and its
    material, looked up once: `material_lanes`), `normal(x, facts)`, `albedo(n, facts)` (Lambert's; 1 for GGX),
    `emitted(facts)`, `lift(x, n, t, facts)`, `visible(p, direction, distance)` -> 1 or 0,
    `reflect(facts, n, view, light)` (a Lambert face's cos θ: a light's a·E·cos θ, as the marched
    faces and voxel GI take it; a GGX face's π·BRDF·cos θ) and `bounce(facts, n, d, u)`."""
    ints = lanes.ints_of if kernel else (lambda x: x.to(torch.int32))
    floats = lanes.floats_of if kernel else (lambda x: x.to(like.dtype))
    r, g = walk_inputs(grid, s, per_lane, ints, kernel=kernel, max_steps=int(voxels.max_steps))
    look = material_lanes(material_table(voxels.materials), s, ints, floats)
    texel = None if voxels.texture is None else atlas_lanes(atlas_table(voxels.texture), s, per_lane, ints, floats)

    cubes = cube_walk(r, g)
    walk = cubes if voxels.rounded is None else rounded_walk(cubes, r, voxels.rounded, per_lane, kernel=kernel)

    def hit(o: list, d: list, t_max):
        found, t, axis, material, (ray, cell), rounded, _ = walk(o, d, t_max)
        normal = face_lanes(axis, d) if rounded is None else rounded
        texels = None
        if texel is not None:  # the face's texel, where the hit lies in its cell
            local = [ray.o[c] + t * ray.d[c] - lanes.to_float(cell[c], t) for c in range(3)]
            texels = texel(material, *face_uv_lanes(local, axis))
        facts = look(material, texels)
        facts.normal = normal
        return lanes.where(found, t, float("inf")), facts

    def albedo(n: list, m: SimpleNamespace) -> list:  # Lambert's goes into the throughput, GGX's is in `reflect`
        return [lanes.where(m.ggx, 1.0, c) for c in m.albedo]

    def reflect(m: SimpleNamespace, n: list, v: list, light: list) -> list:
        ggx = reflectance_lanes(n, v, light, m.albedo, m.roughness, m.metallic)
        lambert = facing(n, light)
        return [lanes.where(m.ggx, c, lambert) for c in ggx]

    # off a rounded box by twice its tracing's threshold: a walk from closer would converge at its start
    clearance = 0.0 if voxels.rounded is None else 2.0 * per_lane(voxels.rounded.threshold) * r.size

    def lift(x: list, n: list, dist) -> list:
        off = LIFT * (r.size + dist) + clearance
        return [x[c] + off * n[c] for c in range(3)]

    def visible(p: list, direction: list, distance):
        return lanes.where(walk(p, direction, distance)[0], 0.0, 1.0)

    return SimpleNamespace(hit=hit, normal=lambda x, m: m.normal, albedo=albedo, emitted=lambda m: m.glow,
                           lift=lambda x, n, dist, m: lift(x, n, dist), visible=visible, reflect=reflect,
                           bounce=ggx_bounce)


def ggx_bounce(m: SimpleNamespace, n: list, d: list, u: list):
    """Where a path arriving along d (three lanes) leaves a face of normal n (three lanes) of
    material `m` (`material_lanes`' look: albedo, roughness, metallic, ggx), and its weight (three
    lanes), from uniform lanes u (three). Lambert: the cosine lobe, weight 1 (the albedo is in the
    throughput). GGX: with probability (1 + metallic)/2 the view mirrored about a half vector drawn
    from the normals the view sees (`visible_normal`), else the cosine lobe; weighted by π·BRDF·cos
    (`ggx.reflectance_lanes`) over π times the mixture's density (one-sample MIS: unbiased, each
    lobe's peaks sampled)."""
    v = [-c for c in d]
    lobe = turn(n, lanes.sqrt(u[0]), u[1])
    alpha = alpha_of(m.roughness)
    h = visible_normal(n, v, alpha, u[0], u[1])
    v_h = lanes.dot3(v, h)
    mirrored = [2.0 * v_h * h[c] - v[c] for c in range(3)]
    p_spec = 0.5 + 0.5 * m.metallic
    light = [lanes.where(m.ggx & (u[2] < p_spec), a, b) for a, b in zip(mirrored, lobe)]
    half = [v[c] + light[c] for c in range(3)]
    norm = lanes.clamp_min(lanes.length3(*half), 1e-12)
    half = [c / norm for c in half]
    n_h_raw = lanes.dot3(n, half)
    n_h = lanes.clamp(n_h_raw, 0.0, 1.0)
    n_v = lanes.clamp_min(lanes.dot3(n, v), 1e-6)
    n_l = lanes.dot3(n, light)
    # the visible normals' density of the mirrored direction: G1(v)·D(h)/(4 n·v) (Heitz 2018, eq. 17)
    pdf = p_spec * _smith_g1(n_v, alpha) * d_ggx(n_h, alpha, sin2_between(n, half, n_h_raw)) / (4.0 * n_v) + (1.0 - p_spec) * lanes.clamp_min(n_l, 0.0) / math.pi
    gain = [lanes.where(n_l > 0.0, c / (math.pi * lanes.clamp_min(pdf, 1e-30)), 0.0)
            for c in reflectance_lanes(n, v, light, m.albedo, m.roughness, m.metallic)]
    return light, [lanes.where(m.ggx, g, 1.0) for g in gain]


def visible_normal(n: list, v: list, alpha, u1, u2) -> list:
    """A GGX microfacet normal of roughness `alpha` about the normal n drawn from the normals the
    view v sees, D_v(h) = G1(v)·max(0, v·h)·D(h)/(n·v) (Heitz 2018, "Sampling the GGX Distribution
    of Visible Normals"): no normal facing away from v, so a mirrored direction's weight F·G2/G1
    stays below 1 where drawing from D(h)·(n·h) gave the grazing views' fireflies. Three lanes."""
    t1, t2 = basis(n)
    local = [alpha * lanes.dot3(v, t1), alpha * lanes.dot3(v, t2), lanes.clamp_min(lanes.dot3(v, n), 1e-6)]  # the view, stretched
    length = lanes.length3(*local)
    vh = [c / length for c in local]
    across = lanes.sqrt(vh[0] * vh[0] + vh[1] * vh[1])
    flat = across > 1e-7
    a = [lanes.where(flat, -vh[1] / lanes.clamp_min(across, 1e-7), 1.0), lanes.where(flat, vh[0] / lanes.clamp_min(across, 1e-7), 0.0)]
    b = [-vh[2] * a[1], vh[2] * a[0], vh[0] * a[1] - vh[1] * a[0]]  # vh × (a, 0)
    r, phi = lanes.sqrt(u1), 2.0 * math.pi * u2
    p1, p2 = r * lanes.cos(phi), r * lanes.sin(phi)
    s = 0.5 * (1.0 + vh[2])
    p2 = (1.0 - s) * lanes.sqrt(lanes.clamp_min(1.0 - p1 * p1, 0.0)) + s * p2
    up = lanes.sqrt(lanes.clamp_min(1.0 - p1 * p1 - p2 * p2, 0.0))
    nh = [p1 * a[0] + p2 * b[0] + up * vh[0], p1 * a[1] + p2 * b[1] + up * vh[1], p2 * b[2] + up * vh[2]]
    h = [alpha * nh[0], alpha * nh[1], lanes.clamp_min(nh[2], 0.0)]  # unstretched
    size = lanes.clamp_min(lanes.length3(*h), 1e-12)
    return [(h[0] * t1[c] + h[1] * t2[c] + h[2] * n[c]) / size for c in range(3)]


def _smith_g1(n_v, alpha):
    """Smith's masking G1(v) of GGX: 2 n·v / (n·v + √(α² + (1 − α²)(n·v)²)), lanes."""
    a2 = alpha * alpha
    return 2.0 * n_v / (n_v + lanes.sqrt(a2 + (1.0 - a2) * n_v * n_v))
