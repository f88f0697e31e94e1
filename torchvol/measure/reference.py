"""References that cost what they must: a scene's converged image, with a measured bound on its own error.

A reference is one rung of a ladder of ever finer renders of a scene with every approximation the
quality levels decide removed (`at_quality`). Rung k:

- marches physically shaded volumes with the error-controlled march (`march.tolerance`) at
  `rung_tolerance(k)` = 1e-2 / 4^k (rays stop under a tenth of it). Volumes in the seeds' alpha
  looks (`shading = "shader"` or `"surface"`) keep the scene's own march: each of their samples
  adds an opacity that does not scale with its length, so their steps are the look, not an
  approximation of an integral that more steps would converge to (docs/QUALITY.md); only their
  early exit, LOD and density threshold go;
- finds the suns' transmittance through volumes with a uniform shadow march of 16·2^k steps or on
  a sun grid of 96·2^k nodes across (box and sphere bounds only, up to MAX_GRID_RESOLUTION),
  whichever evaluates the density fewer times: the march costs about SHADOW_RAYS_PER_PIXEL·steps
  evaluations a pixel, the grid about resolution³ in all (so small images march, large ones use
  the grid, until its resolution would pass the cap);
- doubles every step limit with k: voxel DDA, voxel and fog shadow rays, atmosphere samples;
- renders in float32 while the tolerance is at least FLOAT32_MIN_TOLERANCE, in float64 below it.

Samples per pixel and the render seed are the caller's: renders measured against a reference use
the same seeded sub-samples, so what is left of their error is that of their approximations.

The bound of rung k comes from the differences between successive rungs, d_j = RMSE(rung j − 1,
rung j): where each rung cuts the error by a ratio q, the error left in rung k is the rest of the
geometric series, d_k·q/(1 − q). q is the measured ratio d_k / d_(k−1), taken no lower than 1/2
(the bound is then d_k itself: the ladder is built to cut the error 2-4× a rung, but convergence
slows on sharp-edged clouds, where a tighter q underestimated the error) and no higher than 0.9;
at rung 1, with one difference known, q = 1/2. A `Ladder` starts at rung 1 and climbs (`settle`)
until its bound is `factor` times
under the smallest error it is asked to measure (or under BOUND_FLOOR, or at MAX_RUNG). Rungs are
cached on disk, keyed by a hash of the rung's scene, dtype and seed; the figures behind these
constants are in docs/QUALITY.md.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from ..scene.model import load_scene
from ..scene.quality import QUALITY, Quality, march_settings
from ..version import __version__
from ..volume.shading import SHADINGS

# march keys that only set the approximation: the reference replaces them with its own
APPROXIMATION_KEYS = ("quality", "placement", "steps", "step_size", "step_growth", "dither", "dither_scale",
                      "min_transmittance", "density_threshold", "lod", "tolerance")
BOUND_FLOOR = 1e-5  # RMSE of the display-referred image: under 1% of 8-bit quantisation's 1.1e-3
MAX_RUNG = 4
MIN_RATIO, MAX_RATIO = 0.5, 0.9  # the error ratio between rungs the bound assumes, from the measured one
FLOAT32_MIN_TOLERANCE = 1e-4
# shadow rays a pixel casts in the error-controlled march (two per lit step) on cloud-puff: what the
# choice between shadow march and sun grid assumes
SHADOW_RAYS_PER_PIXEL = 40
MAX_GRID_RESOLUTION = 384  # a 768 grid would hold 1.8 GB of float32 nodes; finer rungs march
MAX_SHADOW_STEPS = 4096  # the schema's limits
MAX_ATMOSPHERE_STEPS = 1024
MAX_FOG_SHADOW_STEPS = 10_000


def reference_overrides(base: Mapping, quality: Quality = "reference") -> dict:
    """The march table at `quality`: approximation keys removed (the alpha integrator is kept: it
    is the shader look, not an approximation)."""
    march = {k: v for k, v in dict(base.get("march") or {}).items() if k not in APPROXIMATION_KEYS}
    if march.get("integrator") != "alpha":
        march.pop("integrator", None)
    march["quality"] = quality
    return march


def at_quality(data: Mapping, quality: Quality) -> dict:
    """A scene dict at level `quality` with every key the level decides removed, so the level sets
    it: the march's approximation keys, `image.spp`, lights' and voxels' `shadow.steps` (and the
    lights' shadow `growth` and `first_step`: the level's shadow steps are uniform, since steps
    grown geometrically for a few steps leave most of a long march in a sliver next to the
    sample), `voxels.max_steps`, `voxels.fog.shadow_steps`, `sky.atmosphere.steps` and `.light_steps` (and the `[atmosphere]` medium's)."""
    data = copy.deepcopy(dict(data))
    data["march"] = reference_overrides(data, quality)
    (data.get("image") or {}).pop("spp", None)
    voxels = data.get("voxels") or {}
    for light in data.get("lights") or []:
        for key in ("steps", "growth", "first_step"):
            (light.get("shadow") or {}).pop(key, None)
    (voxels.get("shadow") or {}).pop("steps", None)
    voxels.pop("max_steps", None)
    (voxels.get("fog") or {}).pop("shadow_steps", None)
    for atmosphere in ((data.get("sky") or {}).get("atmosphere") or {}, data.get("atmosphere") or {}):
        for key in ("steps", "light_steps"):
            atmosphere.pop(key, None)
    return data


def image_error(image: Tensor, reference: Tensor) -> dict[str, float]:
    """RMSE, RMSE relative to the reference's RMS, and PSNR (kornia, peak 1) of `image` against
    `reference`, both (B, 3, H, W) in [0, 1]."""
    from kornia.metrics import psnr

    image, reference = image.float(), reference.float()
    mse = torch.mean((image - reference) ** 2).item()
    rms = math.sqrt(torch.mean(reference**2).item())
    return {"rmse": math.sqrt(mse), "rel_rmse": math.sqrt(mse) / rms if rms > 0 else math.inf,
            "psnr": float(psnr(image, reference, 1.0)) if mse > 0 else math.inf}


def rung_tolerance(k: int) -> float:
    """The error-controlled march's tolerance on rung `k`: 1e-2 / 4^k."""
    return 1e-2 / 4**k


def rung_scene(data: Mapping, k: int, *, spp: int) -> tuple[dict, torch.dtype]:
    """Scene dict and dtype of rung `k` of `data`'s ladder, at `spp` samples per pixel."""
    out = at_quality(data, "reference")
    scene = load_scene(out)  # validated: the kinds of bounds and shading decide the methods
    tolerance, scale, level = rung_tolerance(k), 2**k, QUALITY["reference"]
    march = out["march"]
    march.update(steps=256 * scale, min_transmittance=tolerance / 10)
    if any(SHADINGS[v.shading].caps["semantics"] == "shader" for v in scene.volumes):  # the look's own sampling
        look = march_settings(load_scene(data).march)
        march.update(placement=look.rule.placement, steps=look.rule.steps, step_size=look.rule.step_size,
                     step_growth=look.rule.step_growth, dither=look.dither, dither_scale=look.dither_scale)
    if any(SHADINGS[v.shading].caps["physical"] for v in scene.volumes) and march.get("integrator") != "alpha":
        march["tolerance"] = tolerance
    steps, resolution = min(16 * scale, MAX_SHADOW_STEPS), 96 * scale
    grid = (all(v.bounds.kind in ("box", "sphere") for v in scene.volumes) and resolution <= MAX_GRID_RESOLUTION
            and resolution**3 < scene.image.width * scene.image.height * spp * SHADOW_RAYS_PER_PIXEL * steps)
    for light in out.get("lights") or []:
        if light.get("shadow") is not None:
            light["shadow"] = {"method": "grid", "resolution": resolution} if grid else {"method": "march", "steps": steps}
    out.setdefault("image", {})["spp"] = spp
    voxels = out.get("voxels")
    if voxels:
        voxels["max_steps"] = level.voxel_max_steps * scale
        if voxels.get("shadow") is not None:
            voxels["shadow"]["steps"] = level.voxel_shadow_steps * scale
        if voxels.get("fog") is not None:
            voxels["fog"]["shadow_steps"] = min(level.fog_shadow_steps * scale, MAX_FOG_SHADOW_STEPS)
    steps, light_steps = level.atmosphere_steps
    finer = {"steps": min(steps * scale, MAX_ATMOSPHERE_STEPS), "light_steps": min(light_steps * scale, MAX_ATMOSPHERE_STEPS)}
    if scene.sky is not None and scene.sky.kind == "atmosphere":
        out["sky"]["atmosphere"] = {**(out["sky"].get("atmosphere") or {}), **finer}
    if scene.atmosphere is not None:
        out["atmosphere"] = {**out["atmosphere"], **finer}
    return out, torch.float64 if tolerance < FLOAT32_MIN_TOLERANCE else torch.float32


def _hashable(obj: Any) -> Any:
    if hasattr(obj, "shape"):  # arrays (grids, textures): their bytes, not a truncated repr
        array = np.ascontiguousarray(np.asarray(obj))
        return f"{array.dtype}{array.shape}:{hashlib.sha256(array.tobytes()).hexdigest()}"
    return repr(obj)


def scene_key(data: Any, *, seed: int, dtype: torch.dtype) -> str:
    """A hash of a scene dict (arrays by content), the render seed, dtype and torchvol's version."""
    text = json.dumps([data, seed, str(dtype), __version__], sort_keys=True, default=_hashable)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def cached_render(data: Mapping, *, seed: int, dtype: torch.dtype | None, cache: Path | None,
                  on_chunk: Callable[[int], None] | None = None) -> dict[str, Any]:
    """Render scene dict `data`: {"image", "radiance", "alpha" (1, C, H, W) float32, "time_s",
    "density_evals"}, from `cache` (a folder) when it holds this scene, seed and dtype, else
    rendered and stored there (written under a temporary name: a killed run leaves no partial file)."""
    from ..renderer.executor import render

    path = None if cache is None else Path(cache) / f"render-{scene_key(data, seed=seed, dtype=dtype)}.pt"
    if path is not None and path.is_file():
        return torch.load(path)
    start = time.perf_counter()
    out = render(load_scene(data), seed=seed, dtype=dtype, progress=on_chunk)
    stored = {"image": out.image, "radiance": out.radiance, "alpha": out.alpha,
              "time_s": time.perf_counter() - start, "density_evals": out.stats["density_evals"]}
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_suffix(".partial")
        torch.save(stored, partial)
        partial.replace(path)
    return stored


@dataclass(frozen=True)
class Reference:
    """Rung `rung` of a ladder: `image`, `radiance`, `alpha` (1, C, H, W); `bound`, the RMSE of
    `image` against the converged image at most (where refining halves the error);
    `tolerance` and `dtype` it was marched at; `time_s` its render time (when first rendered)."""

    image: Tensor
    radiance: Tensor
    alpha: Tensor
    bound: float
    rung: int
    tolerance: float
    dtype: str
    time_s: float


class Ladder:
    """The references of one scene (dict `data`) for renders at `spp` samples per pixel and render
    seed `seed`. `cache`: a folder for the rungs. `on_render(k, tolerance)` is called before a
    rung is rendered (not when it comes from the cache); `on_chunk(pixels)` during its render."""

    def __init__(self, data: Mapping, *, seed: int = 0, spp: int = 1, cache: Path | None = None,
                 on_render: Callable[[int, float], None] | None = None, on_chunk: Callable[[int], None] | None = None):
        self.data, self.seed, self.spp, self.cache = copy.deepcopy(dict(data)), seed, spp, cache
        self.on_render, self.on_chunk = on_render, on_chunk
        self.k = 1
        self._rungs: dict[int, dict[str, Any]] = {}

    def rung(self, k: int) -> dict[str, Any]:
        """Rung `k`'s render (`cached_render`'s dict: image, radiance, alpha (1, C, H, W), ...) plus
        its dtype's name, rendered once (or read from the cache)."""
        if k not in self._rungs:
            data, dtype = rung_scene(self.data, k, spp=self.spp)
            path = None if self.cache is None else Path(self.cache) / f"render-{scene_key(data, seed=self.seed, dtype=dtype)}.pt"
            if self.on_render is not None and (path is None or not path.is_file()):
                self.on_render(k, rung_tolerance(k))
            self._rungs[k] = cached_render(data, seed=self.seed, dtype=dtype, cache=self.cache, on_chunk=self.on_chunk)
            self._rungs[k]["dtype"] = str(dtype).removeprefix("torch.")
        return self._rungs[k]

    def reference(self) -> Reference:
        """The current rung, with its bound (rendering it and the rungs under it as needed)."""
        steps = [image_error(self.rung(j - 1)["image"], self.rung(j)["image"])["rmse"] for j in range(1, self.k + 1)]
        if self.k == 1:
            ratio = 0.5
        else:
            ratio = steps[-1] / steps[-2] if steps[-2] > 0 else math.inf
            ratio = min(max(ratio, MIN_RATIO), MAX_RATIO)
        fine = self.rung(self.k)
        return Reference(image=fine["image"], radiance=fine["radiance"], alpha=fine["alpha"],
                         bound=steps[-1] * ratio / (1.0 - ratio), rung=self.k, tolerance=rung_tolerance(self.k),
                         dtype=fine["dtype"], time_s=fine["time_s"])

    def settle(self, images: Sequence[Tensor], *, factor: float) -> Reference:
        """The first reference, from the current rung up, whose bound is `factor` times under the
        smallest error of `images` (each (1, 3, H, W)) against it, or under BOUND_FLOOR; the last
        rung (MAX_RUNG) where none is. The ladder stays on that rung for later calls."""
        while True:
            ref = self.reference()
            smallest = min(image_error(image, ref.image)["rmse"] for image in images)
            if ref.bound <= max(smallest / factor, BOUND_FLOOR) or self.k >= MAX_RUNG:
                return ref
            self.k += 1
