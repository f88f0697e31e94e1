"""Per-scene values are declared once (torchvol/schema.py) and read once (torchvol/batch.py): a
scene batched next to a copy with any one value changed renders, to the bit, as it does alone, or
the pair is refused with a ValueError naming the key. The values are enumerated from the schema
itself: a field added without a base scene that shows it fails `test_bases_cover_every_value`."""

from __future__ import annotations

import copy
import types
import typing
from functools import lru_cache

import numpy as np
import pytest
import torch
from pydantic import BaseModel

import torchvol as tv
from torchvol.scene.model import Scene
from torchvol.scene.quality import at_level
from torchvol.schema.batch import check_same_structure, field_role, structure_key
from torchvol.schema.keypath import lookup, path_str, set_path
from torchvol.schema.models import EACH, SHARED, reachable_models

pytestmark = pytest.mark.slow

SUN = {"kind": "sun", "direction": [-0.6, 0.7, -0.4], "color": [1.0, 0.9, 0.8], "intensity": 3.0}
POINT = {"kind": "point", "position": [0.3, 0.9, -0.8], "color": [0.9, 0.9, 1.0], "intensity": 2.0}
CAMERA = {"eye": [0.4, 0.5, -2.6], "target": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0], "fov_y": 45.0, "roll": 3.0}
SMALL = {"width": 12, "height": 9}
RNG = np.random.default_rng(0)

# Scenes that together hold every model of the schema, each small and lit so that every value shows
def walled_pit(c: torch.Tensor) -> torch.Tensor:
    """Cells [N, 3] of an open-topped pit (material 1) with a blue pillar (2), in solid ground that
    fills the grid to its edges (a larger grid is more ground)."""
    x, y, z = c.unbind(1)
    ground = ((x.abs() >= 4) | (z.abs() >= 4) | (y < -2)) & (y < 1)
    pillar = (x == 1) & (z == 1) & (y < 0)
    return torch.where(ground, 1, torch.where(pillar, 2, 0))


BASES: dict[str, dict] = {
    "physical": {
        "time": 0.5,
        "image": SMALL,
        "camera": CAMERA,
        "sky": {"kind": "constant", "radiance": [0.2, 0.3, 0.5], "halo": {"color": [0.4, 0.3, 0.1], "power": 2.0},
                "flare": {"color": [0.2, 0.1, 0.05], "power": 3.0}},
        "lights": [{**SUN, "shadow": {"steps": 3, "growth": 1.3, "first_step": 0.1}},
                   {**POINT, "shadow": {"steps": 3}}],
        "volumes": [
            {"bounds": {"box": {"min": [-0.7, -0.6, -0.7], "max": [0.7, 0.6, 0.7]}},
             "density": {"fbm": {"octaves": 3, "frequency": 1.7, "seed": 2, "amplitude": 1.2, "bias": 0.4,
                                 "offset": [0.1, 0.2, 0.3], "wind": [0.3, 0.1, 0.2], "radial": 0.4, "center": [0.1, 0.0, 0.0]}},
             "sigma_t": 4.0, "albedo": 0.8, "emission": [0.1, 0.05, 0.0], "phase": {"dual_hg": {"g_forward": 0.6, "g_backward": -0.3, "weight": 0.4}},
             "edge": {"width": 0.2, "base": -0.5}, "multiple_scattering": {"octaves": 2, "a": 0.4, "b": 0.6, "c": 0.7},
             "ambient": {"radiance": [0.3, 0.35, 0.4], "top": [0.5, 0.6, 0.7], "direction": [0.1, 1.0, 0.2], "steps": 2,
                         "sigma_scale": 0.7}},
            {"bounds": {"sphere": {"center": [0.6, -0.2, 0.4], "radius": 0.5}},
             "density": {"exponential": {"value": 1.5, "base": -0.3, "scale_height": 0.6}},
             "sigma_t": 3.0, "albedo": 0.7, "phase": {"hg": {"g": 0.5}}, "ambient": {"visibility": "none"}},
        ],
        "march": {"quality": "draft", "steps": 6, "lod": {"scale": 0.3}, "dither": "hash"},
        "post": {"tonemap": "smoothstep", "exposure": 1.3, "smoothstep_edges": [0.05, 0.9], "vignette": 0.4,
                 "fog": {"color": [0.6, 0.6, 0.7], "density": 0.2}},
    },
    "path": {
        "image": SMALL,
        "camera": CAMERA,
        "lights": [SUN],
        "volumes": [{"bounds": {"box": {"min": [-0.6, -0.5, -0.6], "max": [0.6, 0.5, 0.6]}}, "density": {"constant": 0.8},
                     "sigma_t": 2.5, "albedo": 0.8}],
        "path": {"bounces": 3, "samples": 2},
    },
    "closed form": {
        "image": {**SMALL, "spp": 2},
        "camera": {**CAMERA, "fov_y": None, "focal": 1.2},
        "sky": {"kind": "gradient", "horizon": [0.6, 0.7, 0.8], "slope": [0.2, 0.1, -0.1]},
        "lights": [SUN],
        "volumes": [{"bounds": {"box": {"min": [-0.6, -0.5, -0.6], "max": [0.6, 0.5, 0.6]}}, "density": {"constant": 0.8},
                     "sigma_t": 2.5, "albedo": 0.9, "phase": {"mie": {"g": 0.4}}},
                    {"bounds": {"box": {"min": [-0.3, 0.4, -0.3], "max": [0.3, 0.8, 0.3]}}, "density": {"constant": 0.5},
                     "sigma_t": 2.0, "albedo": 0.5, "phase": "rayleigh"}],
        "march": {"quality": "draft"},
    },
    "grid, tolerance": {
        "image": SMALL,
        "camera": {"matrix": {"K": [[10.0, 0.0, 5.5], [0.0, 10.0, 4.0], [0.0, 0.0, 1.0]],
                              "world_to_camera": [[1.0, 0.0, 0.0, 0.1], [0.0, -1.0, 0.0, 0.05], [0.0, 0.0, 1.0, 2.2],
                                                  [0.0, 0.0, 0.0, 1.0]]}},
        "sky": {"kind": "atmosphere", "atmosphere": {"planet_radius": 6.0e6, "atmosphere_height": 8.0e4, "eye_height": 10.0,
                                                     "rayleigh": [5.8e-6, 13.5e-6, 33.1e-6], "mie": 2.1e-5, "rayleigh_height": 8000.0,
                                                     "mie_height": 1200.0, "mie_g": 0.7, "sun_intensity": 4.0, "steps": 3, "light_steps": 2}},
        "lights": [{**SUN, "direction": [0.3, 0.4, -0.6], "shadow": {"method": "grid", "resolution": 8}}],
        "volumes": [{"bounds": {"box": {"min": [-0.6, -0.6, -0.6], "max": [0.6, 0.6, 0.6]}},
                     "density": {"grid": {"data": RNG.uniform(0.0, 2.0, (4, 5, 6))}},
                     "sigma_t": 3.0, "albedo": 0.9, "phase": {"hg": {"g": -0.3}}}],
        "march": {"quality": "draft", "tolerance": 0.02, "min_transmittance": 0.0, "density_threshold": 0.0},
    },
    "skipped grid": {
        "image": SMALL,
        "camera": CAMERA,
        "lights": [{**SUN, "shadow": {"steps": 2}}],
        "volumes": [{"bounds": {"box": {"min": [-0.6, -0.6, -0.6], "max": [0.6, 0.6, 0.6]}},
                     "density": {"grid": {"data": RNG.uniform(0.0, 2.0, (5, 4, 6)) * (RNG.uniform(size=(5, 4, 6)) > 0.5)}},
                     "sigma_t": 3.0, "albedo": 0.9}],
        "march": {"quality": "draft", "steps": 8, "placement": "count", "max_distance": 5.0, "depth_threshold": 0.05},
    },
    "shader look": {
        "time": 1.5,
        "image": SMALL,
        "camera": {"eye": [0.0, 0.5, 4.0], "target": [0.0, -1.0, 0.0], "focal": 1.5},
        "sky": {"kind": "gradient"},
        "lights": [{**SUN, "direction": [-0.7, 0.3, -0.7]}],
        "volumes": [{"bounds": {"slab": {"y_min": -1.0, "y_max": 1.5}},
                     "density": {"clouds": {"texture": RNG.integers(0, 256, (256, 256, 4), dtype=np.uint8), "octaves": 3,
                                            "density_scale": 1.6, "bias": -0.3, "wind": [0.1, 0.1, 0.8]}},
                     "shading": "shader",
                     "shader": {"light_offset": 0.25, "light_scale": 0.5, "ambient": [0.3, 0.4, 0.5], "ambient_top": [0.9, 1.0, 1.1],
                                "color_lit": [1.0, 0.9, 0.8], "color_dark": [0.2, 0.3, 0.4], "alpha_scale": 0.5, "fog": 0.05}}],
        "march": {"quality": "draft", "integrator": "alpha", "placement": "adaptive", "steps": 24, "step_size": 0.1,
                  "step_growth": 0.03, "dither": "sin", "dither_scale": 0.2, "max_distance": 12.0, "min_transmittance": 0.01,
                  "density_threshold": 0.01},
    },
    "surface look, passes": {
        "image": {**SMALL, "passes": 2, "blend": "exponential", "blend_weight": 0.3},
        "camera": CAMERA,
        "lights": [SUN, POINT],
        "volumes": [{"bounds": {"sphere": {"center": [0.0, 0.0, 0.0], "radius": 1.0}},
                     "density": {"fur": {"center": [0.05, 0.0, -0.05], "radius": 0.5, "length": 0.4, "frequency": 9.0,
                                         "thickness": 0.4, "scale": 1.5, "seed": 3}},
                     "shading": "surface",
                     "surface": {"diffuse": [0.8, 0.5, 0.3], "specular": [0.5, 0.5, 0.6], "shininess": 20.0,
                                 "ambient": [0.05, 0.06, 0.07], "epsilon": 0.02, "gradient": "forward", "alpha_scale": 0.6}}],
        "march": {"quality": "draft", "integrator": "alpha", "placement": "size", "step_size": 0.08, "steps": 40},
    },
    "physical clouds": {
        "image": SMALL,
        "camera": {"eye": [0.0, 0.3, 3.0], "target": [0.0, -0.5, 0.0], "fov_y": 60.0},
        "lights": [SUN],
        "volumes": [{"bounds": {"slab": {"y_min": -1.0, "y_max": 0.5}},
                     "density": {"clouds": {"texture_seed": 4, "octaves": 2}}, "sigma_t": 2.0, "albedo": 0.8}],
        "march": {"quality": "draft", "steps": 8},
    },
    "emission: explosion, colour map, bloom": {
        "time": 0.7,
        "image": SMALL,
        "camera": {"eye": [0.3, 0.4, -2.8], "target": [0.0, 0.0, 0.0], "fov_y": 45.0},
        "lights": [SUN, {**POINT, "position": [0.05, 0.1, 0.0]}, {**POINT, "position": [0.3, -0.2, 0.1], "color": [1.0, 0.5, 0.2]}],
        "volumes": [{"bounds": {"sphere": {"center": [0.0, 0.0, 0.0], "radius": 1.3}},
                     "density": {"explosion": {"center": [0.05, 0.0, 0.0], "radius": 0.8, "growth": 0.2, "displacement": 0.9,
                                               "sharpness": 1.8, "octaves": 3, "frequency": 2.2, "seed": 5,
                                               "offset": [0.3, 0.1, 0.2], "drift": [0.1, 0.7, 0.0]}},
                     "sigma_t": 3.0, "albedo": 0.2,
                     "emission_map": {"explosion": {"center": [0.0, 0.1, 0.0], "radius": 0.9, "scale": 1.5,
                                                    "thin": [1.0, 0.8, 0.6], "dense": [0.5, 0.15, 0.05], "core": [5.0, 6.0, 6.5],
                                                    "edge": [0.7, 0.8, 0.75], "reach": 0.85, "overshoot": 1.1}},
                     "bloom": {"light": 1, "strength": 0.5, "falloff": 1.2}}],
        "march": {"quality": "draft", "steps": 6},
        "post": {"tonemap": "aces"},
    },
    "atmosphere medium": {
        "image": SMALL,
        "camera": {**CAMERA, "target": [0.0, 0.3, 0.0]},
        "lights": [{**SUN, "direction": [-0.6, 0.3, 0.8]}],
        "volumes": [{"bounds": {"sphere": {"center": [0.0, 0.4, 0.0], "radius": 0.4}}, "sigma_t": 2.0, "albedo": 0.8}],
        "atmosphere": {"planet_radius": 50.0, "atmosphere_height": 6.0, "rayleigh": [0.02, 0.05, 0.1], "mie": 0.04,
                       "rayleigh_height": 1.5, "mie_height": 0.4, "mie_g": 0.6, "ground": [0.3, 0.35, 0.2], "steps": 3,
                       "light_steps": 2},
        "march": {"quality": "draft", "steps": 4},
    },
    "cloudscape": {
        "time": 1.0,
        "image": SMALL,
        "camera": {"eye": [0.0, 0.2, 0.0], "target": [0.0, 2.0, 6.0], "fov_y": 70.0},
        "sky": {"kind": "gradient", "horizon": [0.6, 0.7, 0.8], "slope": [0.4, 0.3, 0.0]},
        "lights": [{**SUN, "direction": [0.2, 0.5, 1.0], "shadow": {"steps": 2}}],
        "volumes": [{"bounds": {"shell": {"bottom": 1.0, "top": 3.0, "planet_radius": 300.0}},
                     "density": {"cloudscape": {"seed": 1, "bottom": 1.0, "top": 3.0, "planet_radius": 300.0, "type": 0.8,
                                                "coverage": 0.7, "erosion": 0.8, "scale": 6.0, "detail_scale": 1.5,
                                                "offset": [0.1, 0.2, 0.3], "wind": [0.4, 0.0, 0.3]}},
                     "ambient": {"radiance": [0.2, 0.25, 0.3], "top": [0.6, 0.65, 0.8], "visibility": "none"},
                     "sigma_t": 4.0, "albedo": 0.9, "sky_blend": 0.01}],
        "march": {"quality": "draft", "steps": 8, "max_distance": 30.0},
    },
    "voxels: sdf, glow, rounded, texture": {
        "image": SMALL,
        "camera": {"eye": [5.0, 9.0, -12.0], "target": [0.0, 0.0, 0.0], "fov_y": 50.0},
        "sky": {"kind": "constant", "radiance": [0.2, 0.3, 0.4]},
        "lights": [SUN, {**POINT, "position": [2.0, 8.0, -6.0], "intensity": 40.0}],
        "voxels": {
            "occupancy": {"sdf": {"material": 1, "shape": {"subtraction": {
                "a": {"union": [{"box": {"center": [0.0, 0.0, 0.0], "half_size": [5.0, 4.0, 5.0]}},
                                {"rounded_box": {"center": [0.0, 4.0, 0.0], "half_size": [2.0, 2.0, 2.0], "radius": 0.5}}]},
                "b": {"intersection": [{"sphere": {"center": [0.0, 1.0, 0.0], "radius": 5.5}}]}}}}},
            "cells": {"min": [-7, -6, -7], "max": [7, 8, 7]},
            "origin": [0.1, 0.0, -0.1], "voxel_size": 1.05, "max_steps": 48,
            "materials": [{"color": [0.9, 0.8, 0.7], "emission": [0.1, 0.2, 0.05]}], "face_tones": [0.6, 1.0, 0.8], "ambient": [0.2, 0.25, 0.3],
            "ao": {"gamma": 0.6}, "shadow": {"steps": 24, "offset": 0.05},
            "texture": {"atlas": RNG.integers(0, 256, (8, 8, 3), dtype=np.uint8), "tiles": 2},
            "glow": {"intensity": 0.01, "epsilon": 0.05, "color": [0.4, 0.6, 1.0]},
            "rounded": {"radius_min": 0.1, "radius_range": 0.3, "steps": 5, "threshold": 0.03, "seed": 1, "retries": 3},
        },
        "post": {"fog": {"color": [0.5, 0.5, 0.6], "density": 0.02}},
    },
    "voxels: terrain, fog, hybrid": {
        "image": SMALL,
        "camera": {"eye": [-14.0, 12.0, -14.0], "target": [0.0, 2.0, 0.0], "fov_y": 55.0},
        "sky": {"kind": "constant", "radiance": [0.5, 0.6, 0.7]},
        "lights": [{**SUN, "direction": [-0.4, 0.6, 0.5]}],
        "voxels": {
            "occupancy": {"terrain": {"seed": 3, "base": 1.0, "amplitude": 5.0, "frequency": 0.11, "octaves": 2, "gain": 0.6,
                                      "lacunarity": 2.1, "dirt_depth": 1.5, "materials": [1, 2, 3],
                                      "ores": {"material": 2, "density": 0.8, "seed": 7, "depth": 0.4}}},
            "cells": {"min": [-10, -3, -10], "max": [10, 10, 10]}, "traversal": "hybrid", "max_steps": 64,
            "materials": [{"color": [0.35, 0.7, 0.25], "roughness": 0.2, "metallic": 0.3},
                          {"color": [0.55, 0.4, 0.25], "roughness": 0.5, "metallic": 0.8}, [0.5, 0.5, 0.52]],
            "shadow": {"steps": 32}, "reflections": {"bounces": 2, "steps": 24},
            "fog": {"density": 0.06, "base": 0.5, "scale_height": 5.0, "color": [1.0, 0.95, 0.9], "shadow_steps": 12},
        },
    },
    "voxels: gi": {
        "image": {"width": 8, "height": 6},
        "camera": {"eye": [0.5, 0.5, -2.0], "target": [0.0, -0.5, 2.0], "fov_y": 70.0},
        "sky": {"kind": "constant", "radiance": [0.5, 0.6, 0.8]},
        "lights": [{**SUN, "direction": [0.3, 0.8, 0.4]}],
        "voxels": {
            "occupancy": {"sdf": {"material": 1, "shape": {"subtraction": {
                "a": {"box": {"center": [0.0, 0.0, 0.0], "half_size": [4.0, 3.0, 4.0]}},
                "b": {"union": [{"box": {"center": [0.0, 0.0, 0.0], "half_size": [3.0, 2.0, 3.0]}},
                                {"box": {"center": [1.0, 3.0, 1.0], "half_size": [1.0, 1.0, 1.0]}}]}}}}},
            "cells": {"min": [-5, -4, -5], "max": [5, 4, 5]}, "max_steps": 24,
            "materials": [{"color": [0.8, 0.5, 0.4], "emission": [0.05, 0.1, 0.0]}],
            "gi": {"method": "path", "bounces": 2, "samples": 3, "lod": {"near": 2.0, "far": 3.5, "samples": 1}},
        },
    },
    "voxels: cone": {
        "image": {"width": 8, "height": 6},
        "camera": {"eye": [0.5, 0.5, -2.0], "target": [0.0, -1.5, 2.0], "fov_y": 70.0},
        "sky": {"kind": "constant", "radiance": [0.5, 0.6, 0.8]},
        "lights": [{**SUN, "direction": [0.3, 0.8, 0.4]}],
        "voxels": {
            "occupancy": {"function": {"fn": walled_pit}},
            "cells": {"min": [-6, -4, -6], "max": [6, 4, 6]}, "max_steps": 24,
            "materials": [{"color": [0.8, 0.5, 0.4], "emission": [0.05, 0.1, 0.0]}, [0.3, 0.6, 0.9]],
            "gi": {"method": "cone", "cones": 5, "aperture": 35.0, "steps": 7, "max_distance": 5.0, "ao": True,
                   "lod": {"near": 2.0, "far": 3.5, "cones": 2, "aperture": 55.0}},
        },
    },
    "terrain, cross shadows": {
        "image": SMALL,
        "camera": {"eye": [0.0, 2.0, -5.0], "target": [0.0, 0.0, 2.0], "fov_y": 60.0},
        "sky": {"kind": "constant", "radiance": [0.4, 0.5, 0.7]},
        "lights": [{**SUN, "direction": [0.4, 0.8, 0.3], "shadow": {"steps": 3}}],
        "terrain": {"seed": 4, "base": -0.2, "amplitude": 0.9, "frequency": 0.6, "octaves": 3, "color": [0.3, 0.5, 0.2],
                    "rock_color": [0.5, 0.45, 0.4], "rock_slope": 0.15, "ambient": [0.1, 0.12, 0.15], "steps": 48,
                    "safety": 0.6, "epsilon": 2e-3, "max_distance": 9.0, "shadow_offset": 0.02, "ambient_steps": 3},
        "volumes": [{"bounds": {"slab": {"y_min": 1.2, "y_max": 1.9}},
                     "density": {"fbm": {"octaves": 2, "frequency": 1.1, "seed": 3, "bias": -0.3, "amplitude": 1.5,
                                         "hash": "arithmetic"}},
                     "sigma_t": 3.0, "albedo": 0.9},
                    {"bounds": {"slab": {"y_min": -1.2, "y_max": 0.4}},
                     "density": {"exponential": {"value": 1.0, "base": -0.5, "scale_height": 0.5}}, "sigma_t": 0.8, "albedo": 0.8}],
        "march": {"quality": "draft", "steps": 6, "max_distance": 12.0},
    },
    "particles, god rays": {
        "time": 0.7,
        "image": SMALL,
        "camera": {"eye": [0.0, 0.2, -2.6], "target": [0.0, 0.1, 0.0], "fov_y": 50.0},
        "sky": {"kind": "constant", "radiance": [0.4, 0.5, 0.7]},
        "lights": [{**SUN, "direction": [0.3, 0.2, 1.0], "shadow": {"steps": 2}}],
        "volumes": [{"bounds": {"box": {"min": [-1.0, -1.0, -1.0], "max": [1.0, 1.0, 1.0]}},
                     "density": {"particles": {"count": 5, "seed": 3, "region_min": [-0.5, -0.4, -0.3], "region_max": [0.5, 0.4, 0.3],
                                               "radius": [0.25, 0.45], "speed": 0.3, "wind": [0.1, 0.05, -0.1], "core": 0.3,
                                               "amplitude": 1.4, "frequency": 2.5, "octaves": 2, "noise": "perlin", "edge": 0.6,
                                               "combine": "max"}},
                     "sigma_t": 5.0, "albedo": 0.9}],
        "march": {"quality": "draft", "steps": 6},
        "post": {"god_rays": {"samples": 6, "density": 0.8, "decay": 0.9, "weight": 0.3, "exposure": 0.8, "power": 3.0}},
    },
    "voxels: grid": {
        "image": SMALL,
        "camera": {"eye": [6.0, 7.0, -6.0], "target": [2.0, 1.0, 2.0], "fov_y": 50.0},
        "lights": [SUN],
        "voxels": {"occupancy": {"grid": {"data": RNG.integers(0, 3, (5, 4, 5), dtype=np.uint8)}},
                   "cells": {"min": [-1, 0, 1]}, "materials": [[0.8, 0.2, 0.2], [0.2, 0.8, 0.2]]},
    },
    "voxels: water": {
        "time": 0.4,
        "image": SMALL,
        "camera": {"eye": [-9.0, 6.0, -9.0], "target": [0.0, 0.0, 0.0], "fov_y": 55.0},
        "sky": {"kind": "constant", "radiance": [0.5, 0.6, 0.7]},
        "lights": [{**SUN, "direction": [-0.4, 0.7, 0.5]}],
        "voxels": {
            "occupancy": {"terrain": {"seed": 2, "base": -3.0, "amplitude": 6.0, "frequency": 0.15, "octaves": 2}},
            "cells": {"min": [-8, -4, -8], "max": [8, 5, 8]}, "max_steps": 48,
            "water": {"level": 0.3, "ior": 1.4, "absorption": [0.5, 0.2, 0.1], "fresnel": "schlick", "offset": 0.02,
                      "waves": {"amplitude": 0.1, "frequency": [1.5, 1.2], "speed": [1.1, 0.6]}},
        },
    },
}


# ---------------------------------------------------------------------------------------------
# The values of the schema: every field that holds numbers (or arrays of them)


def _numeric(annotation) -> bool:
    """int/float, tuples/lists of them, arrays (`Any` fields holding data)."""
    base = typing.get_args(annotation)[0] if typing.get_origin(annotation) is typing.Annotated else annotation
    if base in (int, float) or base is typing.Any:
        return True
    args = [a for a in typing.get_args(base) if a is not type(None) and a is not Ellipsis]
    if typing.get_origin(base) in (typing.Union, types.UnionType):
        return any(_numeric(a) for a in args)
    if typing.get_origin(base) in (tuple, list):
        return all(_numeric(a) for a in args)
    return False


def schema_values() -> set[tuple[str, str]]:
    """(model, field) of every numeric field reachable from Scene."""
    return {(cls.__name__, name) for cls in reachable_models(Scene) for name, f in cls.model_fields.items()
            if _numeric(f.annotation) and not (isinstance(f.annotation, type) and issubclass(f.annotation, BaseModel))
            and not callable_field(cls, name)}


def callable_field(cls, name) -> bool:
    return cls.__name__ == "FunctionOccupancy"  # a Python callable, not a value


def leaves(model: BaseModel, raw, loc: tuple = ()):
    """(key path, model class name, field name) of every numeric value a scene sets explicitly
    (`raw`: its data; defaults a scene leaves alone are not its values)."""
    for name, f in type(model).model_fields.items():
        value, given = getattr(model, name), raw.get(name) if isinstance(raw, dict) else None
        if value is None or given is None:
            continue
        here = loc + (name,)
        if isinstance(value, BaseModel):
            yield from leaves(value, given, here)
        elif isinstance(value, list) and value and isinstance(value[0], BaseModel):
            for i, item in enumerate(value):
                yield from leaves(item, given[i], here + (i,))
        elif _numeric(f.annotation) and not isinstance(value, bool) and not callable_field(type(model), name):
            yield here, type(model).__name__, name


@lru_cache(maxsize=None)
def base_scene(name: str) -> Scene:
    return tv.load_scene(BASES[name])


def all_leaves() -> list[tuple[str, tuple]]:
    return [(name, loc) for name in BASES for loc, _, _ in leaves(base_scene(name), BASES[name])]


def test_bases_cover_every_value():
    covered = {(cls, field) for name in BASES for _, cls, field in leaves(base_scene(name), BASES[name])}
    missing = sorted(schema_values() - covered)
    assert not missing, f"no base scene sets these values (add them to BASES): {missing}"


# ---------------------------------------------------------------------------------------------
# Changing one value


def _candidates(value):
    if isinstance(value, np.ndarray):
        yield (255 - value) if value.dtype == np.uint8 else value * 0.5 + 0.25 * (value > 0)
        return
    if isinstance(value, bool):
        return
    if isinstance(value, int):
        yield from (value + 1, value - 1, value + 2)
        return
    if isinstance(value, float):
        yield from (v for v in (value * 1.25 + 0.05, value * 0.8 - 0.01, value + 0.5, value - 0.5, value * 0.5) if v != value)
        return
    for i, item in enumerate(value):  # a tuple: one component at a time
        for changed in _candidates(item):
            out = list(value)
            out[i] = changed
            yield out


def changed_scene(name: str, loc: tuple) -> tuple[Scene, object]:
    """The base scene with the value at `loc` changed to the first valid other value."""
    data = copy.deepcopy(base_scene(name).model_dump())
    value = lookup(data, loc)
    value = np.asarray(value) if loc[-1] in ("data", "atlas", "texture") else value
    for candidate in _candidates(value):
        trial = copy.deepcopy(data)
        set_path(trial, path_str(loc), candidate)
        try:
            return tv.load_scene(trial), candidate
        except ValueError:
            continue
    raise AssertionError(f"{name}: found no valid other value for {path_str(loc)} = {value!r}")


def shared(scene: Scene, changed: Scene) -> bool:
    """Whether the two differ in structure (a shared value): then a batch must refuse them."""
    return structure_key(at_level(scene)) != structure_key(at_level(changed))


def outputs(out, b: int) -> dict[str, torch.Tensor]:
    return {"image": out.image[b], "radiance": out.radiance[b], "depth": out.depth[b], "alpha": out.alpha[b],
            **{k: v[b] for k, v in out.aovs.items()}}


def differences(a: dict, b: dict) -> dict[str, str]:
    out = {}
    for key in a:
        if not torch.equal(a[key], b[key]):
            d = (a[key] - b[key]).abs()
            where = tuple(int(i) for i in torch.nonzero(d == d.max())[0])
            out[key] = f"max {d.max().item():.3g} at {where}"
    return out


@pytest.fixture(scope="module")
def alone():
    return lru_cache(maxsize=None)(lambda name: outputs(tv.render(base_scene(name), seed=2), 0))


@pytest.mark.parametrize("name, loc", all_leaves(), ids=[f"{n}: {path_str(loc)}" for n, loc in all_leaves()])
def test_a_changed_value_renders_as_alone_or_is_refused(name, loc, alone, one_thread):
    scene = base_scene(name)
    changed, value = changed_scene(name, loc)
    if shared(scene, changed):
        with pytest.raises(ValueError) as err:
            tv.render([changed, scene], seed=[1, 2])
        assert path_str(loc) in str(err.value), f"the refusal does not name {path_str(loc)}: {err.value}"
        return
    both = tv.render([changed, scene], seed=[1, 2])
    changed_alone = outputs(tv.render(changed, seed=1), 0)
    assert differences(alone(name), changed_alone), (
        f"{path_str(loc)} = {value!r} does not change the base scene {name!r}: make the base show it")
    assert not differences(outputs(both, 1), alone(name)), (
        f"{name}, second after {path_str(loc)} = {value!r}: {differences(outputs(both, 1), alone(name))}")
    assert not differences(outputs(both, 0), changed_alone), (
        f"{name} with {path_str(loc)} = {value!r}, first in the batch: {differences(outputs(both, 0), changed_alone)}")


def test_refusal_names_the_key_and_both_values():
    a = base_scene("physical")
    b = tv.load_scene(a, {"volumes[0].density.fbm.octaves": 4})
    with pytest.raises(ValueError, match=r"scenes\[1\]\.volumes\[0\]\.density\.fbm\.octaves: got 4; .*scenes\[0\] has 3"):
        check_same_structure([a, b])


def test_roles_are_declared_where_defaults_would_be_wrong():
    """Seeds and arrays are per scene (handled scene by scene); the march is shared as a whole."""
    from torchvol.fields.fbm import FbmDensity
    from torchvol.scene.model import Voxels

    assert field_role(FbmDensity, "seed") is EACH and field_role(FbmDensity, "octaves") is SHARED
    assert field_role(Voxels, "occupancy") is EACH and field_role(Scene, "march") is SHARED


@pytest.mark.parametrize("name", list(BASES) + tv.preset_names())
def test_chunking_changes_nothing(name, one_thread):
    """Any `chunk_rays` gives the same render, to the bit (chunks hold whole pixels)."""
    scene = base_scene(name) if name in BASES else tv.load_scene(tv.preset(name, width=8, height=6), {"image.spp": 2})
    whole = outputs(tv.render(scene, seed=2), 0)
    for chunk_rays in (1, 7, 101):
        out = outputs(tv.render(scene, seed=2, chunk_rays=chunk_rays), 0)
        assert not differences(out, whole), f"chunk_rays={chunk_rays}: {differences(out, whole)}"
