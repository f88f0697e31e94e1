"""Random scenes over every volumetric technique, rendered tiny, checked for what must never happen.

A scene is drawn from the bundled presets that hold media (each a combination of techniques: fire,
explosion, particles, fur, cloudscapes in shells, the seeds' looks, the atmosphere, god rays,
terrain, layers), mixed with media of other presets (so they overlap), given extras (a terrain,
the atmosphere, fog and god rays, accumulation, labels, `[path]` where it can trace them) and hard cases (a camera inside a medium or
under the ground, numbers pushed to zero, to huge values and to the edges of their ranges,
phases with g near ±1). A render must then give no NaN, no Inf, no exception but a `ValueError`
that names a key (`"{path}: got {value!r}; ..."`), and every output in range: image and alpha in
[0, 1], radiance and depth non-negative.
"""

from __future__ import annotations

import copy
import re
import traceback
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import torch

# presets whose scenes hold media (each a family of techniques)
SOURCES = ("atmosphere", "cloud-puff", "cloudscape", "explosion", "fire", "fur-ball", "god-rays",
           "homogeneous-box", "multi-layer", "particles", "template-clouds", "terrain-clouds")
LABELS = ["optical_thickness", "alpha_volumes", "instance"]
PATH_SHARE = 0.3  # of the scenes a path can trace (physical media, a terrain or the atmosphere): traced with `[path]`
# a SceneError names the key first: "volumes[0].sigma_t: got -1.0; ..."
NAMES_A_KEY = re.compile(r"^[A-Za-z_][\w\[\].]*: got ")
EDGES = (0.0, 1e-9, 1e-3, 10.0, 1e6, 1e12)
# a density's values may go past the cap (1e12, `fields.base.DENSITY_MAX`): the schema bounds none
# of them (positions are kept to EDGES: a noise at 1e30 has no meaning to keep finite)
DENSITY_EDGES = EDGES + (1e30,)


@dataclass
class Failure:
    """A scene that broke a promise: its index, the scene (JSON-safe) and what went wrong."""

    index: int
    scene: dict
    error: str


def preset_scene(name: str) -> dict:
    """The preset `name` as a plain scene dict (every key spelt out)."""
    from ..scene.model import preset

    return preset(name).model_dump(mode="json", exclude_none=True)


def random_scene(rng: np.random.Generator, sources: dict[str, dict]) -> dict:
    """One random scene: a preset of `sources` (name -> scene dict), mixed and pushed to its edges."""
    scene = copy.deepcopy(sources[SOURCES[rng.integers(len(SOURCES))]])
    if rng.random() < 0.4:  # media of another preset in the same space
        other = sources[SOURCES[rng.integers(len(SOURCES))]]
        scene["volumes"] = scene.get("volumes", []) + copy.deepcopy(other.get("volumes", []))[:2]
    _extras(rng, scene)
    for _ in range(rng.integers(0, 4)):
        _push(rng, scene)
    _camera(rng, scene)
    scene["image"] = {**scene.get("image", {}), "width": int(rng.integers(6, 17)), "height": int(rng.integers(4, 13))}
    scene["image"].pop("spp", None)
    march = scene.setdefault("march", {})
    march.update(quality="draft", steps=int(rng.integers(2, 17)))
    if rng.random() < 0.15:
        march["tolerance"] = float(rng.choice([1e-2, 1e-3]))
    if rng.random() < 0.15:
        march["closed_form"] = False
    return scene


def _extras(rng: np.random.Generator, scene: dict) -> None:
    """Adds a terrain, the atmosphere, fog and god rays, accumulation: each sometimes."""
    sun = {"kind": "sun", "direction": [float(x) for x in rng.normal(size=3)], "intensity": float(rng.uniform(0.5, 10.0))}
    if rng.random() < 0.5:
        sun["shadow"] = {"steps": int(rng.integers(1, 6)), "method": str(rng.choice(["march", "grid"]))}
        if sun["shadow"]["method"] == "grid":
            sun["shadow"]["resolution"] = 8
    if rng.random() < 0.3:
        scene["lights"] = [sun] + scene.get("lights", [])[:1]
    if rng.random() < 0.2:
        scene["terrain"] = {"amplitude": float(rng.uniform(0.0, 2.0)), "steps": 24, "ambient_steps": 2}
    if rng.random() < 0.15:
        scene.pop("sky", None)
        scene["lights"] = [sun] + [li for li in scene.get("lights", []) if li.get("kind") == "point"][:1]
        scene["atmosphere"] = {"steps": 4, "light_steps": 2,
                               "planet_radius": float(rng.choice([1e3, 6.36e6])), "atmosphere_height": float(rng.choice([10.0, 6e4]))}
    _rebind_blooms(scene)
    post = scene.setdefault("post", {})
    if rng.random() < 0.15:
        post["fog"] = {"density": float(rng.choice([0.0, 0.05, 10.0]))}
    if rng.random() < 0.15:
        post["god_rays"] = {"samples": 4}
    if rng.random() < 0.1:
        scene["image"] = {**scene.get("image", {}), "passes": 2}
        scene["march"] = {**scene.get("march", {}), "dither": "hash"}
    if all(v.get("shading", "physical") == "physical" for v in scene.get("volumes", [])) and rng.random() < PATH_SHARE:
        scene["path"] = {"bounces": int(rng.integers(1, 9)), "samples": int(rng.integers(1, 3)),
                         "single": str(rng.choice(["paths", "march"]))}


def _rebind_blooms(scene: dict) -> None:
    """A bloom glows around a point light: bound to the scene's first one, dropped without one."""
    points = [i for i, li in enumerate(scene.get("lights", [])) if li.get("kind") == "point"]
    for vol in scene.get("volumes", []):
        if "bloom" in vol:
            if points:
                vol["bloom"]["light"] = points[0]
            else:
                del vol["bloom"]


def _leaves(tree: Any, path: tuple = ()) -> list[tuple]:
    """Every (path, value) of a float leaf of a nested dict/list."""
    if isinstance(tree, dict):
        return [leaf for k, v in tree.items() for leaf in _leaves(v, path + (k,))]
    if isinstance(tree, list):
        return [leaf for i, v in enumerate(tree) for leaf in _leaves(v, path + (i,))]
    return [(path, tree)] if isinstance(tree, float) else []


def _push(rng: np.random.Generator, scene: dict) -> None:
    """Pushes one float of the scene to an edge: 0, tiny, huge, negative, or g near ±1."""
    leaves = _leaves({k: v for k, v in scene.items() if k != "camera"})
    if not leaves:
        return
    path, value = leaves[rng.integers(len(leaves))]
    if path[-1] in ("g", "g_forward", "g_backward", "mie_g"):
        new = float(rng.choice([0.999999, -0.999999, 0.99, -0.99]))
    elif rng.random() < 0.1:
        new = -abs(value) - 1.0  # most keys refuse it, naming the key
    else:
        values = "density" in path and not any(k in ("center", "offset", "wind", "drift") for k in path)
        edges = DENSITY_EDGES if values else EDGES  # (a density's values, not where it sits)
        new = float(rng.choice(edges)) * (1.0 if rng.random() < 0.5 else abs(value) + 1.0)
    node = scene
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = new


def _camera(rng: np.random.Generator, scene: dict) -> None:
    """Sometimes puts the camera inside a medium or under the ground."""
    vols, cam = scene.get("volumes", []), scene.setdefault("camera", {})
    roll = rng.random()
    if roll < 0.2 and vols:
        bounds = vols[rng.integers(len(vols))].get("bounds", {})
        inside = None
        if "sphere" in bounds:
            inside = bounds["sphere"].get("center", [0.0, 0.0, 0.0])
        elif "box" in bounds:
            inside = [0.5 * (a + b) for a, b in zip(bounds["box"]["min"], bounds["box"]["max"])]
        if inside is not None:
            cam.pop("matrix", None)
            cam["eye"], cam["target"] = list(inside), [inside[0] + 0.3, inside[1] - 0.2, inside[2] + 1.0]
    elif roll < 0.3:
        cam.pop("matrix", None)
        cam["eye"], cam["target"] = [0.2, -0.5, -3.0], [0.0, 0.3, 0.0]


REFUSED = "refused"


def check(scene: dict, render: Callable[..., Any]) -> str | None:
    """None where `render(scene)` keeps every promise, `REFUSED` where it refused the scene naming
    the key (a promise kept too), else what it broke."""
    lights = scene.get("lights") or []
    sun = bool(lights) and lights[0].get("kind", "sun") == "sun"  # sun_visibility needs one
    try:
        out = render(scene, aovs=LABELS + (["sun_visibility"] if sun else []))
    except ValueError as err:
        return REFUSED if NAMES_A_KEY.match(str(err)) else f"ValueError naming no key: {err}"
    except Exception:  # noqa: BLE001 - any other exception is what the fuzz looks for
        return traceback.format_exc(limit=-6)
    outputs = {"image": out.image, "radiance": out.radiance, "depth": out.depth, "alpha": out.alpha, **out.aovs}
    for name, value in outputs.items():
        if not bool(torch.isfinite(value).all()):
            return f"{name}: non-finite values"
    if out.image.min() < 0 or out.image.max() > 1 or out.alpha.min() < 0 or out.alpha.max() > 1:
        return f"out of [0, 1]: image {out.image.min():.3g}..{out.image.max():.3g}, alpha {out.alpha.min():.3g}..{out.alpha.max():.3g}"
    if out.radiance.min() < 0 or out.depth.min() < 0:
        return f"negative: radiance {out.radiance.min():.3g}, depth {out.depth.min():.3g}"
    return None


def fuzz(count: int, *, seed: int = 0, first: int = 0,
         progress: Callable[[int], None] | None = None) -> tuple[list[Failure], int]:
    """Renders scenes `first` .. `first + count − 1` of the fuzz seeded `seed`; -> (their failures,
    how many were refused with a ValueError naming the key)."""
    from ..renderer.executor import render
    from ..scene.model import preset_names

    sources = {name: preset_scene(name) for name in SOURCES if name in preset_names()}
    failures, refused = [], 0
    for index in range(first, first + count):
        scene = random_scene(np.random.default_rng([seed, index]), sources)
        error = check(scene, render)
        refused += error == REFUSED
        if error not in (None, REFUSED):
            failures.append(Failure(index, scene, error))
        if progress is not None:
            progress(1)
    return failures, refused


__all__ = ["Failure", "check", "fuzz", "random_scene"]
