"""An fbm noise cloud: density = max(bias + amplitude · fbm(frequency · (p − wind·time) + offset)
− radial · |p − center|, 0)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Annotated, Literal

import torch
from pydantic import Field, model_validator
from torch import Tensor

from ..noise import fast as fastnoise
from ..noise import lattice as noise
from ..schema.batch import Stacked, per_scene, take
from ..schema.models import EACH, Strict, Vec3

NOISES = {"value": noise.value_noise, "perlin": noise.perlin_noise, "worley": noise.worley_noise}
# a noise's twin over several scenes at once (points, their scenes' rows, the seeds), bitwise each scene's own
SCENE_NOISES = {noise.value_noise: (noise.value_noise_scenes, noise.scene_rows),
                noise.perlin_noise: (noise.perlin_noise_scenes, noise.scene_rows),
                noise.worley_noise: (noise.worley_noise_scenes, noise.scene_rows)}


class FbmDensity(Strict):
    """density = max(bias + amplitude · fbm(frequency · (p − wind·time) + offset) − radial·|p − center|, 0):
    `radial` > 0 thins the noise out away from `center` (a puff instead of a filled bound)."""

    octaves: int = Field(5, ge=1, le=12)
    frequency: float = Field(1.0, gt=0.0, le=1e6)
    noise: Literal["value", "perlin", "worley"] = "value"
    # how value noise hashes its lattice: "table" (Perlin's permutation gathers, the default) or
    # "arithmetic" (int32 hash: integer arithmetic, no gathers; a different random field with the
    # same statistics: docs/SPEED.md)
    hash: Literal["table", "arithmetic"] = "table"
    seed: Annotated[int, EACH] = 0
    amplitude: float = 1.0
    bias: float = 0.0
    offset: Vec3 = (0.0, 0.0, 0.0)
    wind: Vec3 = (0.0, 0.0, 0.0)
    radial: float = Field(0.0, ge=0.0)
    center: Vec3 = (0.0, 0.0, 0.0)

    @model_validator(mode="after")
    def _hash_of_value_noise(self):
        if self.hash == "arithmetic" and self.noise != "value":
            raise ValueError(f"hash = 'arithmetic' hashes value noise only; noise is {self.noise!r}")
        return self


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
        self.whole = fastnoise.fbm_value_hashed if params.hash == "arithmetic" else None
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
    perm, columns = noise.scene_lattice_tables(tuple(int(x) for x in seeds), "cpu")
    perm, rows = to.ints(perm), to.ints(noise.scene_rows(to.scene))
    if kind == "perlin":
        return lambda x, y, z: noise.perlin_lanes(x, y, z, perm, rows)
    if kind == "worley":
        values = [to.floats(c) for c in columns]
        return lambda x, y, z: noise.worley_lanes(x, y, z, perm, values, rows)
    first = to.floats(columns[0])
    return lambda x, y, z: noise.value_lanes(x, y, z, perm, first, rows)


def fbm_density(q, p, count):
    """The fbm field's signed density in lanes (`ops.lanes`) at p (three lanes), `count` octaves
    kept per lane or None; `q` from `fbm_lanes`."""
    return fastnoise.fbm_field(*p, q.basis, q.scales, count, q, octaves=q.octaves)
