"""An fbm noise cloud: density = max(bias + amplitude · fbm(frequency · (p − wind·time) + offset)
− radial · |p − center|, 0)."""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Annotated, Literal

import torch
from pydantic import Field, model_validator
from torch import Tensor

from ..noise import fast as fastnoise
from ..noise import lattice as noise
from ..ops.grid_ops import cubes, sliding_max
from ..schema.batch import Stacked, per_scene, take
from ..schema.models import EACH, Strict, Vec3

NOISES = {"value": noise.value_noise, "perlin": noise.perlin_noise, "worley": noise.worley_noise}
# a noise's twin over several scenes at once (points, their scenes' rows, the seeds), bitwise each scene's own
SCENE_NOISES = {noise.value_noise: (noise.value_noise_scenes, noise.scene_rows),
                noise.perlin_noise: (noise.perlin_noise_scenes, noise.scene_rows),
                noise.worley_noise: (noise.worley_noise_scenes, noise.scene_rows)}


# how value noise hashes its lattice: "table" (Perlin's permutation gathers, the default) or
# "arithmetic" (int32 hash: integer arithmetic, no gathers; a different random field with the
# same statistics, 1.4-2x faster in the kernels: docs/VOLUMES.md, "A fast fbm")
Hash = Literal["table", "arithmetic"]


def value_noise_hash(params):
    """A density's `hash` and `noise` checked together (the arithmetic hash hashes value noise
    only): its model validator. -> `params`."""
    if params.hash == "arithmetic" and params.noise != "value":
        raise ValueError(f"hash = 'arithmetic' hashes value noise only; noise is {params.noise!r}")
    return params


def whole_fbm(hash: str):
    """The whole-fbm function `seeded_fbm` takes for a value noise hashed by `hash`: the arithmetic
    hash's (`noise.fast.fbm_value_hashed`), or None (the table's octaves through their basis)."""
    return fastnoise.fbm_value_hashed if hash == "arithmetic" else None


class FbmDensity(Strict):
    """density = max(bias + amplitude · fbm(frequency · (p − wind·time) + offset) − radial·|p − center|, 0):
    `radial` > 0 thins the noise out away from `center` (a puff instead of a filled bound)."""

    octaves: int = Field(5, ge=1, le=12)
    frequency: float = Field(1.0, gt=0.0, le=1e6)
    noise: Literal["value", "perlin", "worley"] = "value"
    hash: Hash = "table"
    seed: Annotated[int, EACH] = 0
    amplitude: float = 1.0
    bias: float = 0.0
    offset: Vec3 = (0.0, 0.0, 0.0)
    wind: Vec3 = (0.0, 0.0, 0.0)
    radial: float = Field(0.0, ge=0.0)
    center: Vec3 = (0.0, 0.0, 0.0)

    @model_validator(mode="after")
    def _hash_of_value_noise(self):
        return value_noise_hash(self)


def seeded_fbm(basis, q: Tensor, s: Tensor, params: Stacked, lod: Tensor | None, *, whole=None) -> Tensor:
    """fbm of `basis(x, seed=...)` at `q` [N, 3] of scenes `s` [N], each scene with its own
    `params.seed` and `params.octaves`, `lod` [N] octaves dropped (None: all) -> [N]. `whole`:
    a whole-fbm function with `fastnoise.fbm_value_hashed`'s signature, used instead of `basis`."""
    octaves = None if lod is None else params.octaves - lod
    if whole is None and len(params) > 1 and basis in SCENE_NOISES:  # one pass over all scenes' points
        batched, scene_rows = SCENE_NOISES[basis]
        seeds = [int(x) for x in params.seed]
        return noise.fbm(q, lambda x, rows: batched(x, rows, seeds), octaves=params.octaves, lod=octaves,
                         rows=scene_rows(s))

    def one_scene(b: int, idx: Tensor | slice, q_b: Tensor) -> Tensor:
        seed, lod_b = params.seed[b], None if octaves is None else octaves[idx]
        if whole is not None:
            return whole(q_b, seed=seed, octaves=params.octaves, lod=lod_b)
        return noise.fbm(q_b, lambda x: basis(x, seed=seed), octaves=params.octaves, lod=lod_b)

    return per_scene(q, s, len(params), one_scene)


class FbmField:
    def __init__(self, params: Stacked, times: Tensor):
        self.p = params
        self.basis = NOISES[params.noise]
        self.whole = whole_fbm(params.hash)
        self.shift = params.wind * times[:, None]  # (B, 3)
        self.feature_size = noise.finest_period(params.octaves) / params.frequency

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        return self.signed(points, scene_index, lod).clamp_min(0.0)

    def signed(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        """The fbm field's density before its clamp at 0 (negative: how far from having any): points
        [n, 3], scene_index [n], lod [n] octaves dropped or None -> [n]."""
        p, s = self.p, scene_index
        q = take(p.frequency, s)[:, None] * (points - take(self.shift, s)) + take(p.offset, s)
        f = seeded_fbm(self.basis, q, s, p, lod, whole=self.whole)
        per_point = SimpleNamespace(bias=take(p.bias, s), amplitude=take(p.amplitude, s), radial=take(p.radial, s),
                                    center=take(p.center, s).unbind(1))
        return fastnoise.puff(f, *points.unbind(1), per_point)


MACRO_LATTICE = 1 << 20  # lattice points an octave's local bounds may take (`fbm_macro`); more: its largest value


def fbm_macro(field: FbmField, b: int, low: Tensor, high: Tensor, cells: int) -> tuple[Tensor, Tensor, Tensor] | None:
    """Scene b's fbm's local majorants (`volume.local_majorant`) over cubes tiling its box [low,
    high] ([3] each), `cells` along the longest side -> (bounds (D, H, W), their corner [3], size
    [3]); None unless its noise is value noise. Value noise blends its lattice's values with
    weights in [0, 1], so over a cube an octave stays within the values at the corners of the
    lattice cells the cube touches (its span widened by 1e-4 of its coordinates: the kernel's
    float32 point may round across a lattice face): a sliding maximum over the octave's lattice
    values (weighted, so a negative amplitude takes the least), summed over the octaves with the
    bias, less the radial thinning at the cube's nearest point to the centre. An octave whose
    lattice over the box passes `MACRO_LATTICE` points takes its largest weighted value, the
    declared bound's share."""
    p = field.p
    if p.noise != "value":
        return None
    low, high = low.to(torch.float64), high.to(torch.float64)
    shape, side = cubes(low, high, cells=cells)
    frequency, amplitude = float(p.frequency[b]), float(p.amplitude[b])
    corners = [low[a] + side * torch.arange(shape[a], dtype=torch.float64) for a in range(3)]  # each cube's lowest, per axis
    u = [frequency * (corners[a] - float(field.shift[b, a])) + float(p.offset[b, a]) for a in range(3)]
    basis = fastnoise.value_noise_hashed if p.hash == "arithmetic" else noise.value_noise
    total = torch.full(shape[::-1], float(p.bias[b]), dtype=torch.float64)
    scales = [1.0] + [float(c) for c in noise.folded_scales(int(p.octaves), dtype=torch.float64, device="cpu")]
    for k, scale in enumerate(scales):
        weight = amplitude * 0.5 * 0.5**k
        width = scale * frequency * side
        slack = [1e-4 * (1.0 + scale * float(c.abs().max()) + width) for c in u]  # the kernel's float32 rounding, and more
        start = [torch.floor(scale * c - e) for c, e in zip(u, slack)]  # each cube's first lattice point, per axis
        window = math.ceil(width + 2.0 * max(slack)) + 2  # the most lattice points a cube's span can touch
        first = [float(c.min()) for c in start]
        count = [int(float(c.max()) - f) + window for c, f in zip(start, first)]
        if math.prod(count) > MACRO_LATTICE:
            total = total + max(weight, 0.0)  # value noise lies in [0, 1)
            continue
        axes = torch.meshgrid(*[f + torch.arange(n, dtype=torch.float64) for f, n in zip(first[::-1], count[::-1])],
                              indexing="ij")  # z, y, x
        points = torch.stack(axes[::-1], dim=-1).reshape(-1, 3)
        values = weight * basis(points, seed=int(p.seed[b])).reshape(count[::-1])
        peak = sliding_max(values, window)  # the largest over each window of lattice points
        i = [(c - f).long() for c, f in zip(start, first)]
        total = total + peak[i[2][:, None, None], i[1][None, :, None], i[0][None, None, :]]
    radial = float(p.radial[b])
    if radial > 0.0:  # less its thinning at each cube's point nearest the centre
        centre = [float(p.center[b, a]) for a in range(3)]
        near = [corners[a] + (centre[a] - corners[a]).clamp(0.0, side) - centre[a] for a in range(3)]
        total = total - radial * (near[2][:, None, None] ** 2 + near[1][None, :, None] ** 2 + near[0][None, None, :] ** 2).sqrt()
    # a float32 sum may round a hair above the bound: a margin on the terms' scale, and a cube whose
    # bound is within it of 0 kept (where bias and thinning nearly cancel, float32 may leave density)
    margin = 1e-6 * (abs(float(p.bias[b])) + abs(amplitude) + radial * float((high - low).norm()))
    total = torch.where(total > -margin, total + 2.0 * margin, 0.0)
    return total, low, torch.full((3,), side, dtype=torch.float64)


def fbm_lanes(field: FbmField, to) -> SimpleNamespace:
    """What the fbm takes per lane: its parameters (`to.per_lane`: per scene -> lanes), its noise
    basis over the lanes' scenes (`noise_basis`) and its octave scales (`to.number`)."""
    p = field.p
    q = SimpleNamespace(frequency=to.per_lane(p.frequency), shift=to.per_lane(field.shift), offset=to.per_lane(p.offset),
                        bias=to.per_lane(p.bias), amplitude=to.per_lane(p.amplitude), radial=to.per_lane(p.radial),
                        center=to.per_lane(p.center), octaves=int(p.octaves))
    q.scales = [to.number(c) for c in noise.folded_scales(q.octaves, dtype=torch.float32, device="cpu")]
    q.basis = noise_basis(p.noise, p.seed, p.hash, to)
    return q


def noise_basis(kind: str, seeds, hash: str, to):
    """The noise `kind` ("value", "perlin", "worley") of the lanes' scenes (`to.scene`, each with
    its seed of `seeds`) as `fbm_sum`'s basis: value noise of the arithmetic hash's mixed seeds, or
    a lattice noise over the scenes' tables stacked (`noise.scene_lattice_tables`), each lane's
    chain in its scene's block (`to.ints`, `to.floats`: a table as the backend's array)."""
    if hash == "arithmetic":
        return fastnoise.hashed(to.ints(take(fastnoise.mixed_seeds(seeds, "cpu"), to.scene)))
    noise_perm, columns = noise.scene_lattice_tables(tuple(int(x) for x in seeds), "cpu")
    perm, rows = to.ints(noise_perm), to.ints(noise.scene_rows(to.scene))
    if kind == "perlin":
        return lambda x, y, z: noise.perlin_lanes(x, y, z, perm, rows)
    if kind == "worley":
        values = [to.floats(noise.chained_values(noise_perm, c)) for c in columns]
        return lambda x, y, z: noise.worley_lanes(x, y, z, perm, values, rows)
    chained = to.floats(noise.chained_values(noise_perm, columns[0]))
    return lambda x, y, z: noise.value_lanes(x, y, z, perm, chained, rows)


def planar_basis(seeds, hash: str, to, dtype: torch.dtype):
    """`noise_basis`' value noise on the plane y = 0 (a heightfield's; its y argument, 0, unread),
    bitwise its values there, its tables in `dtype`: the arithmetic hash's from the four y = 0
    corners, or the table's read ahead a cell at a time (`noise.planar_corners`, one table a
    distinct seed of the lanes' scenes)."""
    if hash == "arithmetic":
        return fastnoise.hashed(to.ints(take(fastnoise.mixed_seeds(seeds, "cpu"), to.scene)), plane=True)
    seeds = [int(x) for x in seeds]
    distinct = sorted(set(seeds))
    tables = [noise.planar_corners(seed, dtype) for seed in distinct]
    first = torch.tensor([65536 * distinct.index(seed) for seed in seeds], dtype=torch.int32, device=to.scene.device)
    corners, rows = to.floats(tables[0] if len(tables) == 1 else torch.cat(tables)), to.ints(take(first, to.scene))
    return lambda x, y, z: noise.planar_value_lanes(x, z, corners, rows)


def fbm_density(q, p, count):
    """The fbm field's signed density in lanes (`ops.lanes`) at p (three lanes), `count` octaves
    kept per lane or None; `q` from `fbm_lanes`."""
    return fastnoise.fbm_field(*p, q.basis, q.scales, count, q, octaves=q.octaves)
