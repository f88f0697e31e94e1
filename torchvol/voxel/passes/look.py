"""The marched look of voxel hits, written once in lanes (`ops.lanes`): a hit's shading point
(position, face normal, face UV, material, texel, face tone: seed 001 Steps 5-6), its neighbour
AO (Step 7), each light's Lambert and GGX light with its shadow ray (Step 8, Variant 5) and the
colour they make.

`Shading` runs these functions on torch columns piece by piece (the eager reference: any device
and dtype, each shadow ray traced by the `VoxelTracer` and, where the plan asks, through the
passes beside the voxels), or, where the walks are kernels and no GI replaces the ambient, as one
Dr.Jit kernel over a chunk's hits (`Shading.shade`): the shadow walks (`walk.cube_walk`) and what
the rays meet beside the voxels (`volume.kernel_march.surface_lanes_of`) inside it; the same
functions, the same order of operations."""

from __future__ import annotations

import math
from types import SimpleNamespace

import torch
from torch import Tensor

from ...light.lights import LightSource, point_lanes
from ...ops import lanes
from ...schema.batch import Stacked
from ..dda import next_cell_lanes
from ..ggx import reflectance_lanes
from ..grid import VoxelGrid
from ..materials import VOXEL_MATERIALS, material_lanes, material_table
from ..shade import ao_lanes, atlas_lanes, atlas_table, face_lanes, face_uv_lanes
from ..walk import occupied_lanes, visible_walk, walk_inputs

__all__ = ["direct_lanes", "fusable", "lit_lanes", "look_inputs", "look_tables", "point_lanes_of", "visible_beside"]


def look_tables(voxels: Stacked, plan) -> SimpleNamespace:
    """What `look_inputs` reads of a batch, built once a render: its materials' table
    (`materials.material_table`) and its texture atlases (`shade.atlas_table`, None: none)."""
    return SimpleNamespace(materials=material_table(voxels.materials),
                           atlas=atlas_table(voxels.texture) if plan.texture else None)


def look_inputs(voxels: Stacked, plan, tables: SimpleNamespace, grid: VoxelGrid, lights: list[LightSource], s: Tensor,
                per_lane, ints, floats, *, kernel: bool, walks: bool = True, surface: bool = True,
                light: bool = True) -> SimpleNamespace:
    """What the look's lanes functions take for hits of scenes `s` [n] (`tables`: `look_tables`;
    `per_lane`: per scene -> lanes; `ints`, `floats`: a tensor -> lanes; `kernel`: Dr.Jit's lanes,
    else torch columns): the grids' placement (`origin`, `size`); with `walks` the walk's rays and
    tables (`walk.walk_inputs`: AO's lookups, the shadow walks); with `surface` the materials
    (`materials.material_lanes`), texels and face tones (`point_lanes_of`'s); with `light` the
    ambient, AO's gamma, the shadows' offset and steps, each light's `toward(p)` (on torch with
    what lies on its way, `LightSource.through`), the diffuse material's and GGX's reflectance
    (`reflect`: `ggx.reflectance_lanes`) (`direct_lanes`' and `lit_lanes`'). Only what a caller
    reads: on torch each is a pass over the hits."""
    r, g = walk_inputs(grid, s, per_lane, ints, kernel=kernel, max_steps=int(voxels.max_steps)) if walks else (None, None)
    origin, size = (r.origin, r.size) if walks else (per_lane(grid.origin), per_lane(grid.voxel_size))
    q = SimpleNamespace(r=r, g=g, origin=origin, size=size, ggx=plan.ggx,
                        rounded=voxels.rounded is not None)
    if surface:
        q.look, q.tones = material_lanes(tables.materials, s, ints, floats), per_lane(voxels.face_tones)
        q.texel = atlas_lanes(tables.atlas, s, per_lane, ints, floats) if plan.texture else None
    if light:
        q.ambient, q.diffuse, q.reflect = per_lane(voxels.ambient), VOXEL_MATERIALS["diffuse"].fn, reflectance_lanes
        q.gamma = per_lane(voxels.ao.gamma) if plan.ao else None
        if plan.shadows:
            q.offset, q.shadow_steps = per_lane(voxels.shadow.offset), int(voxels.shadow.steps)
        q.lights = [_toward_lanes(source, per_lane, s) for source in lights]
    return q


def _toward_lanes(light: LightSource, per_lane, s: Tensor):
    """`light.toward` in lanes: toward(p) -> (unit direction to the light, its irradiance (three
    lanes each; through the air where `light.through`, on torch columns), the distance (a lane, or
    inf: a sun))."""
    if light.directional:
        direction, irradiance = per_lane(light.direction), per_lane(light.radiant)
        toward = lambda p: (direction, irradiance, math.inf)  # noqa: E731
    else:
        position, radiant = per_lane(light.params.position), per_lane(light.radiant)
        toward = lambda p: point_lanes(position, radiant, p)  # noqa: E731
    if light.through is None:
        return toward

    def through(p):
        direction, irradiance, distance = toward(p)
        air = lanes.columns(light.through(torch.stack(p, dim=1), s))
        return direction, [e * a for e, a in zip(irradiance, air)], distance

    return through


def point_lanes_of(q: SimpleNamespace, o: list, d: list, t, cell: list, axis, material, normal: list | None = None):
    """The shading point of hits at `t` along rays o, d (three lanes each) on face `axis` of
    `cell` (three int lanes) of `material` (int lanes); `normal` the shading normal where it is
    not the face's (rounded voxels): x, face_normal, normal (three lanes each), u, v (the face UV),
    albedo (its material's, times its texel, times its face's tone; three lanes), emission,
    roughness, metallic, ggx and material (a float lane)."""
    x = [o[c] + t * d[c] for c in range(3)]
    local = [lanes.clamp((x[c] - q.origin[c]) / q.size - lanes.to_float(cell[c], t), 0.0, 1.0) for c in range(3)]
    face = face_lanes(axis, d)
    u, v = face_uv_lanes(local, axis)
    look = q.look(material, None if q.texel is None else q.texel(material, u, v))
    tone = lanes.where(axis == 0, q.tones[0], lanes.where(axis == 1, q.tones[1], q.tones[2]))
    return SimpleNamespace(x=x, cell=cell, axis=axis, face_normal=face, normal=face if normal is None else normal, u=u,
                           v=v, albedo=[a * tone for a in look.albedo], emission=look.glow, roughness=look.roughness,
                           metallic=look.metallic, ggx=look.ggx, material=lanes.to_float(material, t), view=[-c for c in d])


def ao_of(q: SimpleNamespace, point: SimpleNamespace):
    """`shade.ao_lanes` at the hits `point` (`point_lanes_of`): a lane."""
    face = [lanes.to_int32(c) for c in point.face_normal]
    return ao_lanes(occupied_lanes(q.r, q.g), point.cell, face, point.axis, point.u, point.v, q.gamma)


def visible_beside(q: SimpleNamespace, inside: dict | None):
    """`direct_lanes`' visible(l, start, direction, distance) inside a kernel: 1.0 where the shadow
    ray of `q.shadow_steps` cells (`walk.visible_walk`, the tracer's shadow walk) from `start`
    along `direction` (three lanes each) reaches `distance` (a lane; inf: a sun) without meeting an
    occupied cell, else 0.0; times what it meets beside the voxels where light l has occluder lanes
    in `inside` (`volume.kernel_march.occluder_lanes`, by light; None: none), traced only where
    the voxels let the light through."""
    walk = visible_walk(q.r, q.g, lanes.int_like(q.shadow_steps, q.r.base))

    def visible(l, start, direction, distance):
        vis = walk(start, direction, distance)
        return vis if l not in (inside or {}) else vis * inside[l].through(start, direction, distance, vis > 0.0)

    return visible


def shadow_start(q: SimpleNamespace, point: SimpleNamespace, direction: list) -> list:
    """Where a hit's shadow ray towards `direction` starts: `offset` off its face, or, a rounded
    box lying inside its cell, `offset` past the cell's exit along the ray (`dda.next_cell_lanes`)."""
    if not q.rounded:
        return [point.x[c] + q.offset * point.face_normal[c] for c in range(3)]
    og = [(point.x[c] - q.origin[c]) / q.size for c in range(3)]
    leave = next_cell_lanes(tuple(point.cell), tuple(og), tuple(c / q.size for c in direction))[1]
    return [point.x[c] + (leave + q.offset) * direction[c] for c in range(3)]


def direct_lanes(q: SimpleNamespace, point: SimpleNamespace, light: list, visible, shadowed: dict):
    """`light` (three lanes: the ambient or the GI's incoming light) plus each light's Lambert
    irradiance per unit albedo at `point` (in the lights' order), and their GGX reflected radiance
    (three lanes; None without GGX) and the first shadowed light's visibility (None: none). A
    light of index l in `shadowed` casts a shadow ray: `visible(l, start, direction, distance)`
    -> its visibility (a lane), from `shadow_start`."""
    specular, first = None, None
    for l, toward in enumerate(q.lights):
        direction, irradiance, _ = toward(point.x)
        vis = 1.0
        if l in shadowed:
            start = shadow_start(q, point, direction)
            at, _, distance = toward(start)
            vis = visible(l, start, at, distance)
            first = vis if first is None else first
        diffuse = q.diffuse(point.normal, direction, irradiance, vis)
        light = [light[c] + diffuse[c] for c in range(3)]
        if q.ggx:
            term = [(x * irradiance[c]) * vis for c, x in enumerate(
                q.reflect(point.normal, point.view, direction, point.albedo, point.roughness, point.metallic))]
            specular = term if specular is None else [specular[c] + term[c] for c in range(3)]
    return light, specular, first


def lit_lanes(point: SimpleNamespace, ambient: list, light: list, specular, *, ggx: bool, emission: bool) -> list:
    """A hit's colour (three lanes): its albedo times `light` (`direct_lanes`); with `ggx`, a GGX
    material's the albedo times `ambient` (ambient and indirect light stay diffuse) plus
    `specular`; with `emission`, plus what its faces emit."""
    out = [point.albedo[c] * light[c] for c in range(3)]
    if ggx:
        default = (point.roughness >= 1.0) & (point.metallic <= 0.0)  # `materials.default_material`
        glossy = [0.0] * 3 if specular is None else specular  # (no light)
        out = [lanes.where(default, out[c], point.albedo[c] * ambient[c] + glossy[c]) for c in range(3)]
    if emission:
        out = [out[c] + point.emission[c] for c in range(3)]
    return out


def fusable(plan, lights: list[LightSource]) -> bool:
    """Whether a batch's voxel hits may shade as one kernel (`Shading.shade`): no GI or cones (their
    light comes from passes of their own) and no air on a light's way; a shadow ray that also
    crosses the terrain or volumes beside the voxels needs their lanes too (`Shading`'s
    `occluder_lanes`)."""
    return not plan.gi and not plan.cone and all(light.through is None for light in lights)
