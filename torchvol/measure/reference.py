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
- renders in float32 while the tolerance is at least FLOAT32_MIN_TOLERANCE, in float64 below it;
- path-traces a scene with a `[path]` table (`with_every_order` gives one: every order of
  scattering, PATH_BOUNCES scatterings a path) with 4^k times rung 0's paths a pixel (rung 1:
  PATH_PATHS), in float32 (the kernel: noise, not rounding, is its error).

Samples per pixel and the render seed are the caller's: renders measured against a reference use
the same seeded sub-samples, so what is left of their error is that of their approximations.

The bound of rung k comes from the differences between successive rungs, d_j = RMSE(rung j − 1,
rung j): where each rung cuts the error by a ratio q, the error left in rung k is the rest of the
geometric series, d_k·q/(1 − q). q is the measured ratio d_k / d_(k−1), taken no lower than 1/2
(the bound is then d_k itself: the ladder is built to cut the error 2-4× a rung, but convergence
slows on sharp-edged clouds, where a tighter q underestimated the error) and no higher than 0.9;
at rung 1, with one difference known, q = 1/2. A path-traced rung's error is its noise, not a
series: rungs k − 1 and k are independent with variances 4σ² and σ², so d_k² estimates 5σ², and
its bound is PATH_BOUND_SCALE·d_k/√5 (the estimate is tight over many pixels; the margin covers
it and the paths cut at PATH_BOUNCES). A `Ladder` starts at rung 1 and climbs (`settle`)
until its bound is `factor` times
under the smallest error it is asked to measure (or under BOUND_FLOOR, or at MAX_RUNG; a path-traced
ladder at PATH_MAX_RUNG). Rungs are
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
from ..scene.quality import PATH_STAND_INS, QUALITY, Quality, march_settings
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
PATH_BOUNCES = 256  # scatterings a path of an every-order reference (the schema's limit: every order that matters)
PATH_PATHS = 64  # paths a pixel of a path-traced ladder's rung 1 (16 on rung 0, 4× more a rung)
PATH_MAX_RUNG = 3  # 1024 paths a pixel: ~1 min at 64² for cloud-puff on 2 cores (docs/QUALITY.md)
PATH_BOUND_SCALE = 1.5
EVERY_ORDER_FACTOR = 2.0  # an every-order reference climbs until its bound is half the error (its noise taken out of it)
EVERY_ORDER_MODES = ("auto", "always", "never")


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


def with_every_order(data: Mapping) -> dict:
    """A scene dict path-traced with every order of scattering (`[path]`, PATH_BOUNCES scatterings;
    its paths a pixel the ladder's), without the approximations paths leave out (octaves, sky
    light, bloom)."""
    out = copy.deepcopy(dict(data))
    out["path"] = {"bounces": PATH_BOUNCES, "samples": 1, "single": "paths"}  # unbiased: no march in it
    for volume in out.get("volumes") or []:  # what paths leave out: settings of them share one reference (cache)
        for key in PATH_STAND_INS:
            volume.pop(key, None)
    return out


def every_order_applies(data: Mapping, mode: str = "auto") -> bool:
    """Whether a scene dict gets an every-order (path-traced) reference beside its own: "never"
    not; "always" where `[path]` can trace it (physical media, a terrain, Lambert voxels); "auto" where it can and a
    volume has multiple-scattering octaves (an approximation of the orders past the first)."""
    from ..schema.validate import SceneError

    if mode == "never" or data.get("path") is not None:
        return False
    scene = load_scene(data)
    if mode == "auto" and not any(v.multiple_scattering is not None for v in scene.volumes):
        return False
    try:
        load_scene(with_every_order(data))
    except SceneError:
        return False
    return True


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
    if out.get("path") is not None:  # paths: 4× more a rung, in the kernel's float32
        out["path"] = {**out["path"], "samples": max(1, math.ceil(PATH_PATHS / 4 / spp)) * 4**k}
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
    return out, torch.float64 if tolerance < FLOAT32_MIN_TOLERANCE and out.get("path") is None else torch.float32


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
    `tolerance` and `dtype` it was marched at; `time_s` its render time (when first rendered);
    `noise` the RMSE of its own noise (a path-traced rung's; 0 for a march), which `error_against`
    takes out of an error measured against it."""

    image: Tensor
    radiance: Tensor
    alpha: Tensor
    bound: float
    rung: int
    tolerance: float
    dtype: str
    time_s: float
    noise: float = 0.0

    def error_against(self, image: Tensor) -> dict[str, float]:
        """`image_error` of `image` against this reference, its own noise taken out of the RMSE:
        E[RMSE²] = error² + noise² where the noise is independent of the image."""
        raw = image_error(image, self.image)
        rms = image_error(torch.zeros_like(self.image), self.image)["rmse"]
        rmse = math.sqrt(max(raw["rmse"] ** 2 - self.noise**2, 0.0))
        return {"rmse": rmse, "rel_rmse": rmse / rms if rms > 0 else math.inf}


class Ladder:
    """The references of one scene (dict `data`) for renders at `spp` samples per pixel and render
    seed `seed`. `cache`: a folder for the rungs. `on_render(k, tolerance)` is called before a
    rung is rendered (not when it comes from the cache); `on_chunk(pixels)` during its render."""

    def __init__(self, data: Mapping, *, seed: int = 0, spp: int = 1, cache: Path | None = None,
                 on_render: Callable[[int, float], None] | None = None, on_chunk: Callable[[int], None] | None = None):
        self.data, self.seed, self.spp, self.cache = copy.deepcopy(dict(data)), seed, spp, cache
        self.on_render, self.on_chunk = on_render, on_chunk
        self.k = 1
        self.traced = self.data.get("path") is not None  # rungs of more paths (their noise the error), else finer marches
        self.max_rung = PATH_MAX_RUNG if self.traced else MAX_RUNG
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
        fine, noise = self.rung(self.k), 0.0
        if self.traced:  # independent rungs of σ² and 4σ²: d_k² estimates 5σ²
            noise = steps[-1] / math.sqrt(5.0)
            bound = PATH_BOUND_SCALE * noise
        else:
            ratio = 0.5 if self.k == 1 else (steps[-1] / steps[-2] if steps[-2] > 0 else math.inf)
            ratio = min(max(ratio, MIN_RATIO), MAX_RATIO)
            bound = steps[-1] * ratio / (1.0 - ratio)
        return Reference(image=fine["image"], radiance=fine["radiance"], alpha=fine["alpha"],
                         bound=bound, rung=self.k, tolerance=rung_tolerance(self.k),
                         dtype=fine["dtype"], time_s=fine["time_s"], noise=noise)

    def settle(self, images: Sequence[Tensor], *, factor: float) -> Reference:
        """The first reference, from the current rung up, whose bound is `factor` times under the
        smallest error of `images` (each (1, 3, H, W)) against it, or under BOUND_FLOOR; the last
        rung (`max_rung`) where none is. The ladder stays on that rung for later calls."""
        while True:
            ref = self.reference()
            smallest = min(image_error(image, ref.image)["rmse"] for image in images)
            if ref.bound <= max(smallest / factor, BOUND_FLOOR) or self.k >= self.max_rung:
                return ref
            self.k += 1
