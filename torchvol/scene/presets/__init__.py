"""Bundled scenes (one TOML each) and their documented parameters.

`preset(name, **params)`: every preset takes `width` and `height`; others as listed in PARAMS.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import tomllib

from ...schema.validate import did_you_mean, fail, integer

HERE = Path(__file__).parent


def _template_clouds(data: dict, *, time: float = 0.0, mouse=(0.0, 0.0), noise_texture: Any = None) -> None:
    """The template's mainImage camera: m = iMouse.xy / iResolution.xy;
    ro = 4·normalize(sin 3m.x, 0.8 m.y, cos 3m.x) + (0, 0.5, 0); ta = (0, −1, 0); roll cr = 0.07 cos(0.25 t)."""
    w, h = data["image"]["width"], data["image"]["height"]
    mouse = tuple(mouse)
    if len(mouse) != 2:
        fail("mouse", mouse, "expected (x, y) in pixels")
    mx, my = mouse[0] / w, mouse[1] / h
    ro = np.array([math.sin(3.0 * mx), 0.8 * my, math.cos(3.0 * mx)])
    ro = 4.0 * ro / np.linalg.norm(ro)
    ro[1] += 0.5
    cr = 0.07 * math.cos(0.25 * time)
    data["time"] = time
    data["camera"].update(eye=ro.tolist(), up=[math.sin(cr), math.cos(cr), 0.0])
    if noise_texture is not None:
        clouds = data["volumes"][0]["density"]["clouds"]
        clouds["texture"] = str(noise_texture) if isinstance(noise_texture, (str, Path)) else noise_texture


# cloud-puff's suns: (direction towards the sun, colour, intensity, sky radiance)
CLOUD_PUFF_SUNS = {
    "day": ([0.5, 0.8, -0.6], [1.0, 0.95, 0.88], 10.0, [0.3, 0.45, 0.8]),
    "sunset": ([-0.9, 0.12, -0.3], [1.0, 0.55, 0.25], 10.0, [0.3, 0.26, 0.36]),
    "backlit": ([-0.15, 0.35, 1.0], [1.0, 0.95, 0.88], 10.0, [0.3, 0.45, 0.8]),
}


def _cloud_puff(data: dict, *, sigma_t: float | None = None, g: float | None = None, steps: int | None = None,
                sun: str = "day", realism: bool = True) -> None:
    """`sun`: "day" (over the camera's shoulder), "sunset" (low, warm, from the side) or "backlit"
    (behind the cloud: a silver lining); `realism` False: plain single scattering (no ambient, no
    multiple-scattering octaves, no edge fade), what accuracy checks of the march measure."""
    vol = data["volumes"][0]
    if sigma_t is not None:
        vol["sigma_t"] = sigma_t
    if g is not None:
        vol["phase"] = {"hg": {"g": g}}
    if steps is not None:
        data["lights"][0]["shadow"]["steps"] = steps
    if sun not in CLOUD_PUFF_SUNS:
        fail("cloud-puff.sun", sun, "expected one of " + ", ".join(CLOUD_PUFF_SUNS))
    if sun != "day":
        direction, color, intensity, sky = CLOUD_PUFF_SUNS[sun]
        data["lights"][0].update(direction=direction, color=color, intensity=intensity)
        data["sky"]["radiance"] = sky
    if not isinstance(realism, bool):
        fail("cloud-puff.realism", realism, "expected true or false")
    if not realism:
        for key in ("ambient", "multiple_scattering", "edge"):
            vol.pop(key, None)


def shader_camera_matrix(width: int, height: int, eye, focal: float = 0.8) -> dict:
    """The voxel seed's camera as K and world_to_camera: ray = (0, 0, focal) + sx·(1, 0, 0) +
    sy·(0, H/W, 0) with (sx, sy) = 2·fragCoord/res − 1. Pixel centres give fx = fy = focal·W/2,
    cx = W/2 − 0.5, cy = H/2 − 0.5; camera x = world +x, camera y = world −y, z = +z: R = diag(1, −1, 1),
    a mirrored camera (det −1)."""
    f = focal * width / 2.0
    ex, ey, ez = (float(v) for v in eye)
    return {
        "K": [[f, 0.0, width / 2.0 - 0.5], [0.0, f, height / 2.0 - 0.5], [0.0, 0.0, 1.0]],
        "world_to_camera": [[1.0, 0.0, 0.0, -ex], [0.0, -1.0, 0.0, ey], [0.0, 0.0, 1.0, -ez], [0.0, 0.0, 0.0, 1.0]],
    }


def _vec3_param(name: str, v) -> list[float]:
    v = list(v) if isinstance(v, (list, tuple, np.ndarray)) else None
    if v is None or len(v) != 3 or not all(isinstance(x, (int, float)) and math.isfinite(x) for x in v):
        fail(name, v, "expected three finite numbers")
    return [float(x) for x in v]


def _voxel_carved_box(data: dict, *, eye=(0.0, 2.0, -12.0), sun_dir=(-0.5, 0.6, 0.7)) -> None:
    eye = _vec3_param("voxel-carved-box.eye", eye)
    sun = np.asarray(_vec3_param("voxel-carved-box.sun_dir", sun_dir))
    if np.linalg.norm(sun) == 0:
        fail("voxel-carved-box.sun_dir", sun_dir, "expected a non-zero vector")
    w, h = data["image"]["width"], data["image"]["height"]
    data["camera"] = {"matrix": shader_camera_matrix(w, h, eye)}
    data["lights"][0]["direction"] = (sun / np.linalg.norm(sun)).tolist()


def _voxel_terrain(data: dict, *, size: int | None = None, seed: int | None = None, traversal: str | None = None) -> None:
    vx = data["voxels"]
    if size is not None:
        integer("voxel-terrain.size", size, low=2)  # cells per side
        scale = size / 64  # the default 64-cell landscape, scaled
        lo, hi = -(size // 2), size - size // 2
        vx["cells"] = {"min": [lo, -max(1, round(8 * scale)), lo], "max": [hi, max(2, round(24 * scale)), hi]}
        vx["max_steps"] = 8 * size
        terrain = vx["occupancy"]["terrain"]
        terrain["amplitude"] = 10.0 * scale
        terrain["frequency"] = 0.05 / scale
        data["camera"]["eye"] = [-40.0 * scale, 30.0 * scale, -40.0 * scale]
        data["camera"]["target"] = [0.0, 4.0 * scale, 0.0]
    if seed is not None:
        vx["occupancy"]["terrain"]["seed"] = seed
    if traversal is not None:
        vx["traversal"] = traversal


def _voxel_glow(data: dict, *, intensity: float | None = None) -> None:
    if intensity is not None:
        data["voxels"]["glow"]["intensity"] = intensity


def _voxel_rounded(data: dict, *, seed: int | None = None) -> None:
    if seed is not None:
        data["voxels"]["rounded"]["seed"] = seed


def _voxel_fog(data: dict, *, density: float | None = None) -> None:
    if density is not None:
        data["voxels"]["fog"]["density"] = density


def _emissive(data: dict, *, time: float = 0.0, seed: int | None = None) -> None:
    """explosion, fire: `time` animates the explosion densities (growth, drift; a sphere bound
    grows with its ball); `seed` picks their noise (volume i gets seed + i)."""
    if not (isinstance(time, (int, float)) and math.isfinite(time)):
        fail("time", time, "expected a finite number of seconds")
    data["time"] = float(time)
    for vol in data["volumes"]:  # a sphere around a growing ball grows with it
        growth, sphere = vol["density"]["explosion"].get("growth", 0.0), vol["bounds"].get("sphere")
        if sphere is not None:
            sphere["radius"] *= 1.0 + growth * max(float(time), 0.0)
    if seed is not None:
        integer("seed", seed, low=0)
        for i, vol in enumerate(data["volumes"]):
            vol["density"]["explosion"]["seed"] = seed + i


# the atmosphere preset's views: the TOML's (space), a sunset from the ground, the sky from 10 km up
ATMOSPHERE_VIEWS = {
    "space": {},
    "ground": {"camera": {"eye": [0.0, 2.0, 0.0], "target": [0.0, 3.5, 10.0], "fov_y": 70.0}, "sun": [0.3, 0.08, 1.0]},
    "air": {"camera": {"eye": [0.0, 1.0e4, 0.0], "target": [0.0, 9.0e3, 1.0e4], "fov_y": 60.0}, "sun": [0.5, 0.15, 1.0]},
}


def _atmosphere(data: dict, *, view: str = "space") -> None:
    if view not in ATMOSPHERE_VIEWS:
        fail("atmosphere.view", view, f"expected one of {', '.join(ATMOSPHERE_VIEWS)}")
    setting = ATMOSPHERE_VIEWS[view]
    if setting:
        data["camera"] = dict(setting["camera"])
        data["lights"][0]["direction"] = list(setting["sun"])


def _cloudscape(data: dict, *, coverage: float | None = None, cloud_type: float | None = None,
                sun_elevation: float | None = None, time: float | None = None) -> None:
    """coverage and cloud_type (0 stratus … 1 cumulonimbus) of the layer; the sun's elevation in
    degrees, keeping its azimuth; time moves the clouds with a wind of 0.5 along +x."""
    clouds = data["volumes"][0]["density"]["cloudscape"]
    if coverage is not None:
        clouds["coverage"] = coverage
    if cloud_type is not None:
        clouds["type"] = cloud_type
    if sun_elevation is not None:
        if not isinstance(sun_elevation, (int, float)) or not -90.0 < sun_elevation < 90.0:
            fail("cloudscape.sun_elevation", sun_elevation, "expected degrees in (-90, 90)")
        x, _, z = data["lights"][0]["direction"]
        flat = math.hypot(x, z)
        e = math.radians(sun_elevation)
        data["lights"][0]["direction"] = [x / flat * math.cos(e), math.sin(e), z / flat * math.cos(e)]
    if time is not None:
        data["time"] = time
        clouds["wind"] = [0.5, 0.0, 0.0]


def _particles(data: dict, *, time: float | None = None, seed: int | None = None, count: int | None = None) -> None:
    particles = data["volumes"][0]["density"]["particles"]
    if time is not None:
        data["time"] = time
    if seed is not None:
        particles["seed"] = seed
    if count is not None:
        particles["count"] = count


def _god_rays(data: dict, *, method: str = "both", seed: int = 2) -> None:
    """`method`: "physical" (shadowed haze, no post effect), "screen" (the post effect, no haze)
    or "both"; `seed` the canopy's noise (its holes)."""
    if method not in ("both", "physical", "screen"):
        fail("god-rays.method", method, "expected 'both', 'physical' or 'screen'")
    integer("god-rays.seed", seed, low=0)
    data["volumes"][0]["density"]["fbm"]["seed"] = seed
    if method == "screen":
        del data["volumes"][1]
    if method == "physical":
        del data["post"]["god_rays"]


def cornell_grid() -> np.ndarray:
    """The voxel-gi preset's 12³ material grid[k, j, i]: red (2) left and green (3) right walls,
    white (1) floor, ceiling and back wall with an emissive panel (4) in the ceiling, open at the
    front (k = 0), a tall and a short white block."""
    g = np.zeros((12, 12, 12), dtype=np.uint8)
    g[:, 0, :] = g[:, 11, :] = g[11, :, :] = 1
    g[:, :, 0], g[:, :, 11] = 3, 2  # (the camera looks along +z: +x is screen left)
    g[4:8, 11, 4:8] = 4
    g[6:9, 1:7, 2:5] = 1  # tall block
    g[3:6, 1:4, 7:10] = 1  # short block
    return g


def _voxel_gi(data: dict, *, bounces: int | None = None, samples: int | None = None) -> None:
    data["voxels"]["occupancy"] = {"grid": {"data": cornell_grid()}}
    gi = data["voxels"]["gi"]
    if bounces is not None:
        gi["bounces"] = integer("voxel-gi.bounces", bounces, low=1)
    if samples is not None:
        gi["samples"] = integer("voxel-gi.samples", samples, low=1)
def voxel_pbr_grid() -> np.ndarray:
    """The voxel-pbr preset's grid[k, j, i] of half-unit voxels over world [-9, 9] × [0, 8] × [-9, 9]
    (cells (-18, 0, -18) .. (17, 15, 17)): a floor slab (material 1), a gold ball (2), a plastic cube
    (3) and a stone pillar (4)."""
    k, j, i = np.meshgrid(np.arange(36) - 18, np.arange(16), np.arange(36) - 18, indexing="ij")
    x, y, z = (i + 0.5) * 0.5, (j + 0.5) * 0.5, (k + 0.5) * 0.5  # cell centres (world)
    grid = np.zeros(x.shape, dtype=np.uint8)
    grid[y < 0.5] = 1
    grid[(x + 3.5) ** 2 + (y - 3.0) ** 2 + (z - 1.0) ** 2 < 2.5 ** 2] = 2
    grid[(abs(x - 1.5) < 1.5) & (y > 0.5) & (y < 3.5) & (abs(z + 3.5) < 1.5)] = 3
    grid[(abs(x - 5.0) < 1.0) & (y > 0.5) & (y < 6.0) & (abs(z - 3.0) < 1.0)] = 4
    return grid


def _voxel_pbr(data: dict, *, floor_roughness: float | None = None) -> None:
    """`floor_roughness`: the floor material's roughness (0: a mirror)."""
    if floor_roughness is not None:
        data["voxels"]["materials"][0]["roughness"] = floor_roughness
    data["voxels"]["occupancy"] = {"grid": {"data": voxel_pbr_grid()}}


def courtyard_grid() -> np.ndarray:
    """The voxel-cone preset's 32 × 16 × 32 material grid[k, j, i]: a white floor (1), a red wall (2)
    on the +x side and a green one (3) at the back (+z), a white pillar, a low white block, a blue
    cube (4), a white roof over the back corner with a warm lamp block (5) in its shade."""
    g = np.zeros((32, 16, 32), dtype=np.uint8)
    g[:, 0, :] = 1
    g[:, :12, 30:] = 2
    g[30:, :12, :30] = 3
    g[16:20, 1:11, 8:12] = 1  # pillar
    g[8:14, 1:5, 18:24] = 1  # low block
    g[6:11, 1:6, 3:8] = 4  # blue cube
    g[20:30, 9:11, 19:30] = 1  # roof over the back corner
    g[24:27, 1:3, 23:26] = 5  # the lamp under it
    return g


def _voxel_cone(data: dict, *, cones: int | None = None, ao: bool | None = None) -> None:
    """`cones`: diffuse cones per pixel; `ao`: cone AO on the albedo."""
    data["voxels"]["occupancy"] = {"grid": {"data": courtyard_grid()}}
    if cones is not None:
        data["voxels"]["gi"]["cones"] = integer("voxel-cone.cones", cones, low=1)
    if ao is not None:
        data["voxels"]["gi"]["ao"] = bool(ao)


PARAMS: dict[str, Callable[..., None]] = {
    "atmosphere": _atmosphere,
    "explosion": _emissive,
    "fire": _emissive,
    "god-rays": _god_rays,
    "particles": _particles,
    "voxel-terrain": _voxel_terrain,
    "voxel-glow": _voxel_glow,
    "voxel-rounded": _voxel_rounded,
    "voxel-fog": _voxel_fog,
    "voxel-carved-box": _voxel_carved_box,
    "voxel-gi": _voxel_gi,
    "voxel-cone": _voxel_cone,
    "voxel-pbr": _voxel_pbr,
    "template-clouds": _template_clouds,
    "cloud-puff": _cloud_puff,
    "cloudscape": _cloudscape,
}


def preset_dict(name: str, **params: Any) -> dict:
    """The preset's scene as a dict, with `params` applied (width, height, then the preset's own)."""
    with open(HERE / f"{name}.toml", "rb") as f:
        data = tomllib.load(f)
    for key in ("width", "height"):
        if key in params:
            data["image"][key] = params.pop(key)
    apply = PARAMS.get(name)
    allowed = ["width", "height"] + (list(apply.__kwdefaults__) if apply else [])
    for key in params:
        if key not in allowed:
            fail(f"{name}.{key}", params[key], f"unknown preset parameter; allowed: {', '.join(allowed)}{did_you_mean(key, allowed)}")
    if apply is not None:
        apply(data, **params)  # also with no params: the defaults fill what the TOML leaves out
    return data
