"""The physical march as one Dr.Jit kernel (`torchvol.volume.kernel_march`): held to the eager
march (the reference, `compile="off"`) within the tolerance table on the recipe that uses it and
on every variant it renders; its bytes the same alone and in a batch, for any chunking and thread
count; the plan taking it by default where it renders the technique and eager elsewhere."""

import math
import os
from pathlib import Path

import pytest
import torch
from conftest import TOL
from hypothesis import given, settings
from hypothesis import strategies as st

import torchvol as tv
from torchvol.dataset.recipe import Recipe
from torchvol.measure.mitsuba import puff_grid
from torchvol.runtime.compilation import drjit_available

pytestmark = pytest.mark.skipif(not drjit_available(), reason="Dr.Jit's LLVM backend is not available")
CLOUDS = Path(__file__).resolve().parents[2] / "datasets" / "clouds.toml"
SIZE = {"image.width": 24, "image.height": 20}
# kernel against eager, float32: the same samples and formulas, rounded apart by fused multiply-adds
# and the order of a few sums (measured at 128²: 9e-6 at most on the tonemapped image)
KERNEL_TOL = {"radiance": 5 * TOL[torch.float32], "depth": 5 * TOL[torch.float32]}


def _scene(index: int = 0, **overrides):
    return Recipe.load(CLOUDS, {**SIZE, **overrides}).sample_with_params(index, 0)[0]


def _close(kernel, eager, what: str):
    for name in ("radiance", "alpha", "depth"):
        a, b = getattr(kernel, name), getattr(eager, name)
        err = (a - b).abs()
        worst = int(err.argmax())
        tol = KERNEL_TOL["depth" if name == "depth" else "radiance"] * max(1.0, float(b.abs().max()))
        assert float(err.max()) <= tol, (f"{what}: {name} off by {float(err.max()):.3g} (tolerance {tol:.3g}) at flat "
                                         f"index {worst}: kernel {float(a.flatten()[worst])}, eager {float(b.flatten()[worst])}")


def _both(scene, **kw):
    kernel = tv.render(scene, **kw)
    assert set(kernel.stats["plan"]["marches"].values()) == {"drjit"}, kernel.stats["plan"]["marches"]
    eager = tv.render(scene, compile="off", **kw)
    assert set(eager.stats["plan"]["marches"].values()) == {"eager"}
    return kernel, eager


@pytest.mark.parametrize("index", [0, 1, 2, 3, 4])
def test_recipe_samples_match_the_eager_march(index):
    """clouds.toml, the main job: fbm puff, edge with a base, dual HG, a shadowed sun, octaves,
    sky light with its visibility march."""
    kernel, eager = _both(_scene(index))
    _close(kernel, eager, f"clouds.toml sample {index}")
    assert kernel.stats["density_evals"] > 0
    # the same samples: the evaluations the kernel counts are the eager march's
    assert kernel.stats["density_evals"] == eager.stats["density_evals"]


VARIANTS = {
    "the table hash": {"volumes.0.density.fbm.hash": "table"},
    "fbm of gradient (Perlin) noise": {"volumes.0.density.fbm.hash": "table", "volumes.0.density.fbm.noise": "perlin"},
    "fbm of Worley noise": {"volumes.0.density.fbm.hash": "table", "volumes.0.density.fbm.noise": "worley"},
    "constant density": {"volumes.0.density": {"constant": 1.0}},
    "exponential density in a slab": {"volumes.0.bounds": {"slab": {"y_min": -1.0, "y_max": 0.5}}, "volumes.0.sigma_t": 2.0,
                                      "volumes.0.density": {"exponential": {"value": 1.0, "base": -1.0, "scale_height": 0.5}}},
    "fbm in a slab": {"volumes.0.bounds": {"slab": {"y_min": -1.0, "y_max": 0.5}}},
    "a point light beside the sun": {"lights": [
        {"kind": "sun", "direction": [0.3, 0.9, 0.2], "intensity": 5.0, "shadow": {"steps": 4}},
        {"kind": "point", "position": [0.2, 1.5, 0.3], "intensity": 3.0, "color": [1.0, 0.6, 0.3], "shadow": {"steps": 3}}]},
    "a point light, HG, single scattering": {
        "lights": [{"kind": "point", "position": [0.2, 1.5, 0.3], "intensity": 3.0, "shadow": {"steps": 3}}],
        "volumes.0.phase": {"hg": {"g": 0.5}}, "volumes.0.multiple_scattering": None},
    "a point light, Mie with octaves": {"lights": [{"kind": "point", "position": [-1.2, 0.5, 0.3], "intensity": 2.0}],
                                        "volumes.0.phase": {"mie": {"g": 0.5}}},
    "a point light, Rayleigh with octaves": {"lights": [{"kind": "point", "position": [0.0, 0.0, 0.0], "intensity": 1.0}],
                                             "volumes.0.phase": "rayleigh"},
    "emission": {"volumes.0.emission": [0.5, 0.2, 0.1]},
    "box, no edge": {"volumes.0.bounds": {"box": {"min": [-1, -1, -1], "max": [1, 1, 1]}}, "volumes.0.edge": None},
    "hg, single scattering": {"volumes.0.phase": {"hg": {"g": 0.6}}, "volumes.0.multiple_scattering": None},
    "unshadowed sun, no sky light": {"lights": [{"kind": "sun", "direction": [0.3, 0.9, 0.2], "intensity": 5.0}],
                                     "volumes.0.ambient": None},
    "sky light without visibility": {"volumes.0.ambient": {"visibility": "none"}},
    "lod, no dither, early stop": {"march.lod": {"scale": 0.8}, "march.dither": "none", "march.min_transmittance": 0.05},
    "size placement": {"march.step_size": 0.05},
    "the Riemann sum": {"march.integrator": "riemann"},
    "the seeds' alpha compositing": {"march.integrator": "alpha"},
    "two suns, shadow steps from the light": {"lights": [
        {"kind": "sun", "direction": [0.3, 0.9, 0.2], "intensity": 5.0, "shadow": {"steps": 4, "first_step": 0.1}},
        {"kind": "sun", "direction": [-0.5, 0.2, 0.8], "intensity": 3.0, "shadow": {"steps": 3, "growth": 1.5}}]},
}


@pytest.mark.parametrize("name", list(VARIANTS))
def test_every_variant_the_kernel_renders_matches_the_eager_march(name):
    kernel, eager = _both(_scene(1, **VARIANTS[name]))
    _close(kernel, eager, name)


@pytest.mark.parametrize(("hash_", "kind"), [("arithmetic", "value"), ("table", "value"), ("table", "perlin"),
                                             ("table", "worley")])
def test_the_same_bytes_alone_in_a_batch_for_any_chunking_and_thread_count(hash_, kind):
    """Each scene's noise from its own seed's tables, whatever the scenes beside it."""
    scenes = [_scene(i, **{"volumes.0.density.fbm.hash": hash_, "volumes.0.density.fbm.noise": kind}) for i in range(3)]
    batch = tv.render(scenes, seed=[5, 6, 7])
    for b, scene in enumerate(scenes):
        alone = tv.render(scene, seed=5 + b, chunk_rays=97)
        assert torch.equal(alone.radiance[0], batch.radiance[b]) and torch.equal(alone.depth[0], batch.depth[b])
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = tv.render(scenes[0], seed=5)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(one.radiance[0], batch.radiance[0])


@pytest.mark.parametrize("name", ["cloud-puff", "explosion", "fire", "god-rays", "multi-layer", "terrain-clouds",
                                  "particles", "fur-ball"])
def test_the_presets_match_the_eager_march(name):
    """cloud-puff (table-hash fbm), explosion (its density, colour map and the point light's
    bloom), and the joint march: fire (two explosions sharing space), god-rays (the haze's shadow
    rays marched through the canopy), multi-layer (octaves, sky light through the other volume,
    shadows looked up in the sun's grids), terrain-clouds (shadow and sky rays sphere-traced
    against the terrain), particles (a loop over the particles, each one's fbm where a sample is
    inside it), fur-ball (Worley strands lit as a surface: the normal's six density samples)."""
    kernel, eager = _both(tv.preset(name, width=32, height=24))
    _close(kernel, eager, name)
    assert kernel.stats["density_evals_by_volume"] == eager.stats["density_evals_by_volume"]
    # the same passes, the kernel's inside its march; eager names a shadow ray's pass through another
    # volume only where one crossed it, the kernel every one the plan has
    assert set(eager.stats["passes"]) <= set(kernel.stats["passes"]) <= set(kernel.stats["plan"]["passes"])


@pytest.mark.parametrize(("name", "kind"), [("explosion", "explosion"), ("particles", "particles")])
def test_explosions_and_particles_hashed_arithmetically_match_the_eager_march(name, kind):
    """`hash = "arithmetic"` on the other value-noise densities: the kernel's noise basis and the
    eager whole fbm (`fields.fbm.whole_fbm`) agree, and the noise is another draw than the table's."""
    scene = tv.preset(name, width=32, height=24).model_dump()
    table = tv.render(scene)
    scene["volumes"][0]["density"][kind]["hash"] = "arithmetic"
    kernel, eager = _both(scene)
    _close(kernel, eager, f"{name}, arithmetic hash")
    assert not torch.equal(kernel.radiance, table.radiance)


SUN = {"kind": "sun", "direction": [0.3, 0.9, 0.2], "intensity": 5.0, "shadow": {"steps": 4}}
PUFF = {"bounds": {"sphere": {"center": [0.0, 0.0, 0.0], "radius": 1.0}}, "sigma_t": 6.0, "albedo": 0.9,
        "density": {"fbm": {"octaves": 3, "frequency": 2.0, "seed": 4, "bias": 0.1}}, "phase": {"hg": {"g": 0.5}}}
FOG = {"bounds": {"box": {"min": [-2.0, -1.5, -2.0], "max": [2.0, 0.3, 2.0]}}, "sigma_t": 0.8, "albedo": 0.8,
       "density": {"exponential": {"value": 1.0, "base": -1.5, "scale_height": 0.6}}}


def _media(volumes, lights=(SUN,), **extra):
    sky = {} if "atmosphere" in extra else {"sky": {"kind": "constant", "radiance": [0.3, 0.4, 0.6]}}  # (the air's own)
    return {"image": {"width": 24, "height": 20}, "camera": {"eye": [0.3, 0.6, -3.5], "target": [0.0, 0.0, 0.0], "fov_y": 50.0},
            **sky, "lights": list(lights), "volumes": list(volumes), "march": {"steps": 24}, **extra}


JOINT = {
    "a cloud in fog": _media([PUFF, FOG]),
    "the fog first, three media": _media([FOG, PUFF, {**PUFF, "bounds": {"box": {"min": [0.2, -0.8, -0.5], "max": [1.5, 0.8, 0.5]}},
                                                     "density": {"constant": 0.7}, "emission": [0.2, 0.1, 0.0]}]),
    "grid shadows, sky light, octaves": _media(
        [{**PUFF, "ambient": {"visibility": "march", "steps": 2}, "multiple_scattering": {"octaves": 3}}, FOG],
        lights=[{**SUN, "shadow": {"method": "grid", "resolution": 32}}]),
    "a point light, early stop": _media([PUFF, FOG], lights=[SUN, {"kind": "point", "position": [0.5, 1.2, -0.5],
                                                                   "intensity": 2.0, "shadow": {"steps": 3}}],
                                        march={"steps": 24, "min_transmittance": 0.05}),
    "a sky blend, a graded ambient": _media([{**PUFF, "sky_blend": 0.05, "ambient": {"radiance": [0.2, 0.3, 0.5],
                                                                                      "top": [0.9, 1.0, 1.1], "steps": 2}},
                                             {**FOG, "sky_blend": 0.2}]),
}


@pytest.mark.parametrize("name", list(JOINT))
def test_media_sharing_space_match_the_eager_joint_march(name):
    kernel, eager = _both(JOINT[name], aovs=["alpha_volumes"])
    assert kernel.stats["plan"]["joint"] == eager.stats["plan"]["joint"]
    _close(kernel, eager, name)
    shares = (kernel.aovs["alpha_volumes"] - eager.aovs["alpha_volumes"]).abs().max()
    assert shares <= KERNEL_TOL["radiance"], f"{name}: each medium's share of alpha off by {float(shares):.3g}"
    assert kernel.stats["density_evals_by_volume"] == eager.stats["density_evals_by_volume"]
    assert kernel.stats["march_steps"] == eager.stats["march_steps"]


def _roofed(volumes, lights=(SUN,)):
    """`volumes` over a voxel floor with a roof over its −x half and a pillar: every shadow and
    sky ray of theirs walks the voxels."""
    def cells(c):
        return ((c[:, 1] == -2) | ((c[:, 1] == 1) & (c[:, 0] < 0)) | ((c[:, 0] == 1) & (c[:, 2] == 0))).long()

    return _media(volumes, lights, voxels={"occupancy": {"function": {"fn": cells}}, "cells": {"min": [-3, -2, -3],
                  "max": [3, 1, 3]}, "voxel_size": 0.9, "materials": [[0.7, 0.7, 0.7]], "shadow": {"steps": 12}})


BESIDE_VOXELS = {
    "a cloud, a sun and a point light": _roofed([PUFF], lights=[SUN, {"kind": "point", "position": [0.5, 1.2, -0.5],
                                                                     "intensity": 2.0, "shadow": {"steps": 3}}]),
    "a cloud in fog, grid shadows, sky light": _roofed(
        [{**PUFF, "ambient": {"visibility": "march", "steps": 2}, "multiple_scattering": {"octaves": 3}}, FOG],
        lights=[{**SUN, "shadow": {"method": "grid", "resolution": 32}}]),
}


@pytest.mark.parametrize("name", list(BESIDE_VOXELS))
def test_media_whose_shadow_rays_cross_the_voxels_match_the_eager_march(name, monkeypatch):
    """The voxels' shadow walk (`walk.visible_walk`) inside the march's kernel, before the other
    volumes, as eager's `occluder_transmittance` walks it; the sky rays too."""
    kernel, eager = _both(BESIDE_VOXELS[name])
    _close(kernel, eager, name)
    assert kernel.stats["density_evals_by_volume"] == eager.stats["density_evals_by_volume"]
    assert "volume0.shadow0.voxels" in set(kernel.stats["passes"]) & set(eager.stats["passes"])
    # the walk is what makes them agree: a kernel whose voxels let every ray through is far off
    from torchvol.renderer.surfaces import VoxelOccluder

    monkeypatch.setattr(VoxelOccluder, "visibility_lanes", lambda self, s, per_lane: lambda p, d, far: 1.0)
    unwalked = tv.render(BESIDE_VOXELS[name])
    assert (unwalked.radiance - eager.radiance).abs().max() > 20 * KERNEL_TOL["radiance"]


# a small planet's air (ground y = 0) thick enough to tint a scene of a few units; media lifted above it
AIR = {"planet_radius": 2000.0, "atmosphere_height": 40.0, "rayleigh": [0.02, 0.045, 0.11], "mie": 0.05,
       "rayleigh_height": 8.0, "mie_height": 1.5, "steps": 6, "light_steps": 3}
PUFF_UP = {**PUFF, "bounds": {"sphere": {"center": [0.0, 3.0, 0.0], "radius": 1.0}}}
FOG_UP = {**FOG, "bounds": {"box": {"min": [-2.0, 1.5, -2.0], "max": [2.0, 3.3, 2.0]}},
          "density": {"exponential": {"value": 1.0, "base": 1.5, "scale_height": 0.6}}}
UP = {"eye": [0.3, 3.6, -3.5], "target": [0.0, 3.0, 0.0], "fov_y": 50.0}
IN_THE_AIR = {
    "a cloud in fog": _media([PUFF_UP, FOG_UP], atmosphere=AIR, camera=UP),
    "down onto the ground, a point light": _media(
        [PUFF_UP, FOG_UP], lights=[SUN, {"kind": "point", "position": [0.5, 4.2, -0.5], "intensity": 2.0, "shadow": {"steps": 3}}],
        atmosphere=AIR, camera={**UP, "eye": [0.3, 7.0, -4.0], "target": [0.0, 0.0, 1.0]}),
    "one volume, octaves, sky light": _media(
        [{**PUFF_UP, "ambient": {"radiance": [0.2, 0.3, 0.5], "visibility": "march", "steps": 2},
          "multiple_scattering": {"octaves": 3}}],
        atmosphere=AIR, camera=UP),
}


@pytest.mark.parametrize("name", list(IN_THE_AIR))
def test_media_in_the_air_match_the_eager_joint_march(name):
    """The [atmosphere]'s air a medium of the kernel's joint march: its in-scatter, its
    transmittance in front of every source, its pieces alone in its own step count, the sun
    reaching each sample through it."""
    kernel, eager = _both(IN_THE_AIR[name], aovs=["alpha_volumes"])
    assert kernel.stats["plan"]["air"] == "drjit" and eager.stats["plan"]["air"] == "eager"
    _close(kernel, eager, name)
    shares = (kernel.aovs["alpha_volumes"] - eager.aovs["alpha_volumes"]).abs().max()
    assert shares <= KERNEL_TOL["radiance"], f"{name}: each medium's share of alpha off by {float(shares):.3g}"
    assert kernel.stats["density_evals_by_volume"] == eager.stats["density_evals_by_volume"]
    assert kernel.stats["march_steps"] == eager.stats["march_steps"]
    # the air is seen: without it the picture differs by far more than the tolerance
    bare = tv.render({k: v for k, v in IN_THE_AIR[name].items() if k != "atmosphere"})
    assert (bare.radiance - kernel.radiance).abs().max() > 100 * KERNEL_TOL["radiance"]


@pytest.mark.parametrize("view", ["space", "ground", "air"])
def test_the_atmosphere_preset_matches_the_eager_march(view):
    scene = tv.preset("atmosphere", width=32, height=24, view=view)
    kernel, eager = tv.render(scene), tv.render(scene, compile="off")
    assert kernel.stats["plan"]["air"] == "drjit" and eager.stats["plan"]["air"] == "eager"
    _close(kernel, eager, f"atmosphere, {view}")
    assert kernel.stats["march_steps"] == eager.stats["march_steps"] > 0


@pytest.mark.parametrize("view", ["space", "ground"])
def test_the_sun_depth_table_in_the_kernel_matches_eager_and_the_march(view):
    """`sun_depth = "table"`: the table built by a kernel (float32) and looked up in the march's
    kernel, against eager's (built in float64), and against the nested march it tabulates: within
    1e-3 of the image's peak (measured: 4e-4 on the ground, 1e-4 from space)."""
    scene = tv.preset("atmosphere", width=32, height=24, view=view).model_dump()
    march = tv.render(scene)
    scene["atmosphere"]["sun_depth"] = "table"
    kernel, eager = tv.render(scene), tv.render(scene, compile="off")
    _close(kernel, eager, f"the table, {view}")
    peak = float(march.radiance.abs().max())
    err = float((kernel.radiance - march.radiance).abs().max())
    assert 0 < err <= 1e-3 * peak, f"{view}: the table {err:.3g} from the march (peak {peak:.3g})"


def test_each_scene_of_a_batch_looks_up_its_own_sun_depth_table():
    base = tv.preset("atmosphere", width=24, height=16, view="ground").model_dump()
    scenes = []
    for heights in ((7000.0, 1000.0), (9000.0, 2000.0)):
        scene = {**base, "atmosphere": {**base["atmosphere"], "sun_depth": "table", "rayleigh_height": heights[0],
                                        "mie_height": heights[1]}}
        scenes.append(scene)
    batch = tv.render(scenes, seed=[1, 2])
    for b, scene in enumerate(scenes):
        alone = tv.render(scene, seed=1 + b, chunk_rays=57)
        assert torch.equal(alone.radiance[0], batch.radiance[b])
    assert not torch.equal(batch.radiance[0], batch.radiance[1])


@pytest.mark.parametrize("sun_elevation", [35.0, 2.0, -4.0])
def test_the_atmosphere_sky_in_the_kernel_matches_the_eager_sky(sun_elevation):
    """The `atmosphere` sky's per-pixel march (`light.atmosphere.single_scatter_lanes`) traced by
    Dr.Jit: every direction, up, along the horizon and down to the ground, a sun high, low and set."""
    scene = {"image": {"width": 24, "height": 20}, "camera": {"eye": [0.0, 0.0, 0.0], "target": [0.0, 0.2, 1.0], "fov_y": 120.0},
             "sky": {"kind": "atmosphere", "atmosphere": {"eye_height": 200.0, "mie": 5e-5}},
             "lights": [{"direction": [0.0, math.sin(math.radians(sun_elevation)), math.cos(math.radians(sun_elevation))]}]}
    kernel, eager = tv.render(scene), tv.render(scene, compile="off")
    assert kernel.stats["plan"]["sky"] == "drjit" and eager.stats["plan"]["sky"] == "eager"
    _close(kernel, eager, f"the atmosphere sky, sun at {sun_elevation}°")
    assert float(eager.radiance.max()) > 0
    scene["sky"]["atmosphere"]["sun_depth"] = "table"  # its nested march looked up in the table
    kernel, eager = tv.render(scene), tv.render(scene, compile="off")
    _close(kernel, eager, f"the atmosphere sky from its table, sun at {sun_elevation}°")


def test_the_air_gives_the_same_bytes_alone_in_a_batch_and_for_any_chunking():
    scenes = [IN_THE_AIR["a cloud in fog"], _media([{**PUFF_UP, "sigma_t": 3.0}, {**FOG_UP, "sigma_t": 0.3}],
                                                   atmosphere={**AIR, "mie": 0.2}, camera={**UP, "eye": [-0.5, 4.0, -3.0]})]
    batch = tv.render(scenes, seed=[1, 2])
    for b, scene in enumerate(scenes):
        alone = tv.render(scene, seed=1 + b, chunk_rays=57)
        assert torch.equal(alone.radiance[0], batch.radiance[b]) and torch.equal(alone.depth[0], batch.depth[b])


def test_the_joint_kernel_gives_the_same_bytes_alone_in_a_batch_and_for_any_chunking():
    scenes = [JOINT["a cloud in fog"], _media([{**PUFF, "sigma_t": 3.0, "density": {"fbm": {"octaves": 3, "seed": 9}}},
                                               {**FOG, "sigma_t": 0.3}], lights=[{**SUN, "direction": [-0.4, 0.8, 0.1]}])]
    batch = tv.render(scenes, seed=[1, 2])
    for b, scene in enumerate(scenes):
        alone = tv.render(scene, seed=1 + b, chunk_rays=53)
        assert torch.equal(alone.radiance[0], batch.radiance[b]) and torch.equal(alone.depth[0], batch.depth[b])


MEDIA = CLOUDS.parent / "media.toml"


@pytest.mark.parametrize("index", [6, 10, 14])
def test_media_samples_of_a_grid_density_march_in_the_kernel(index):
    """media.toml's grid samples (a 4³ blob): its density in lanes (`fields.grid.grid_density`)."""
    scene = Recipe.load(MEDIA, SIZE).sample_with_params(index, 0)[0]
    assert scene.volumes[0].density.kind == "grid", "the recipe's draws moved: pick its grid samples again"
    kernel, eager = _both(scene)
    _close(kernel, eager, f"media.toml sample {index}")


GRID = {"bounds": {"box": {"min": [-1.1, -0.8, -0.9], "max": [1.0, 0.9, 1.2]}}, "sigma_t": 8.0, "albedo": 0.9,
        "density": {"grid": {"data": puff_grid(12)}}, "phase": {"hg": {"g": 0.5}}}
GRIDS = {
    "a shadowed sun": _media([GRID]),
    "size placement": _media([GRID], march={"step_size": 0.04}),
    "size placement, a step limit cuts, no dither": _media([GRID], march={"placement": "size", "step_size": 0.03,
                                                                                    "steps": 40, "dither": "none"}),
    "camera inside, early stop, Riemann": {**_media([GRID], march={"steps": 24, "min_transmittance": 0.05,
                                                                   "integrator": "riemann"}),
                                           "camera": {"eye": [0.1, 0.05, -0.3], "target": [0.3, 0.1, 1.0], "fov_y": 70.0}},
    "a point light, emission, an edge fade": _media(
        [{**GRID, "emission": [0.3, 0.1, 0.0], "edge": {"width": 0.2}}],
        lights=[SUN, {"kind": "point", "position": [0.2, 0.3, -0.2], "intensity": 2.0, "shadow": {"steps": 3}}]),
    "grid shadows, sky light marched": _media([{**GRID, "ambient": {"visibility": "march", "steps": 2}}],
                                              lights=[{**SUN, "shadow": {"method": "grid", "resolution": 32}}]),
    "in fog: the joint march over its occupied span": _media([GRID, FOG]),
}


# where the kernel skips empty space too (`plan.kernel_strategy`): a volume alone by count
# placement marches its whole chord on the skipped march's lattice
SKIPPED_IN_KERNEL = {"size placement", "size placement, a step limit cuts, no dither",
                     "in fog: the joint march over its occupied span"}


@pytest.mark.parametrize("name", list(GRIDS))
def test_grid_media_match_the_eager_march(name):
    """A grid's density in lanes (`fields.grid.grid_density`), every output within the tolerance
    table of the eager march, which skips empty space. Where the kernel skips it too it starts and
    stops each ray where eager does (`march.occupied_start`): the same march steps (eager counts
    more density evaluations: for a cheap field it keeps finished rays in its batch a while,
    evaluated at zero-length steps); elsewhere it samples the empty space too."""
    kernel, eager = _both(GRIDS[name])
    _close(kernel, eager, name)
    assert float(kernel.alpha.max()) > 0.5 and "volume0.skip" in eager.stats["passes"]
    skips = "volume0.skip" in kernel.stats["plan"]["passes"]
    assert skips == (name in SKIPPED_IN_KERNEL)
    if skips:
        assert kernel.stats["march_steps"] == eager.stats["march_steps"]
        assert 0 < kernel.stats["density_evals"] <= eager.stats["density_evals"]
    else:
        assert kernel.stats["march_steps"] > eager.stats["march_steps"]


@pytest.mark.parametrize("with_fbm", [False, True], ids=["alone", "beside an fbm"])
def test_grids_of_other_shapes_give_the_same_bytes_alone_and_in_a_batch(with_fbm):
    """Scenes of one batch may hold grids of other shapes (`data` is per scene): the kernel looks
    each lane up in its own scene's grid of the batch's one table; with an fbm beside it, the
    joint march."""
    other = {**GRID, "sigma_t": 5.0, "density": {"grid": {"data": puff_grid(10, seed=3)[:, 2:8]}}}
    extra = [[PUFF], [{**PUFF, "density": {"fbm": {"octaves": 3, "seed": 9}}}]] if with_fbm else [[], []]
    scenes = [_media([GRID, *extra[0]]), _media([other, *extra[1]], lights=[{**SUN, "direction": [-0.4, 0.8, 0.1]}])]
    kernel, eager = _both(scenes, seed=[1, 2])
    _close(kernel, eager, "a batch of two grids")
    for b, scene in enumerate(scenes):
        alone = tv.render(scene, seed=1 + b, chunk_rays=53)
        assert torch.equal(alone.radiance[0], kernel.radiance[b]) and torch.equal(alone.depth[0], kernel.depth[b])
    assert not torch.equal(kernel.alpha[0], kernel.alpha[1])


def _particles(seed: int, combine: str, kind: str = "value"):
    return {**PUFF, "bounds": {"box": {"min": [-1.5, -1.2, -1.2], "max": [1.5, 1.2, 1.2]}},
            "density": {"particles": {"count": 7, "seed": seed, "region_min": [-0.8, -0.5, -0.5], "region_max": [0.8, 0.5, 0.5],
                                      "radius": [0.3, 0.6], "core": -0.2, "amplitude": 2.0, "octaves": 3, "combine": combine,
                                      "noise": kind}}}


@pytest.mark.parametrize(("combine", "kind"), [("sum", "value"), ("max", "value"), ("sum", "perlin"), ("max", "worley")])
def test_particles_match_eager_and_give_the_same_bytes_alone_and_in_a_batch(combine, kind):
    scenes = [_media([_particles(seed, combine, kind)]) for seed in (3, 4)]
    for scene in scenes:
        kernel, eager = _both(scene)
        _close(kernel, eager, f"particles, {combine}, {kind} noise")
        assert kernel.stats["density_evals"] == eager.stats["density_evals"]
    batch = tv.render(scenes, seed=[1, 2])
    for b, scene in enumerate(scenes):
        alone = tv.render(scene, seed=1 + b, chunk_rays=61)
        assert torch.equal(alone.radiance[0], batch.radiance[b])


CLOUDSCAPE = "volumes.0.density.cloudscape"
SHELL = {"volumes.0.bounds": {"shell": {"planet_radius": 300.0, "bottom": 1.5, "top": 4.0}}, f"{CLOUDSCAPE}.planet_radius": 300.0}
CLOUDSCAPES = {
    "the preset (a shell, graded ambient, sky blend)": {},
    "flat ground in a slab": {"volumes.0.bounds": {"slab": {"y_min": 1.5, "y_max": 4.0}}, f"{CLOUDSCAPE}.planet_radius": None},
    "stratus over a small planet": {**SHELL, f"{CLOUDSCAPE}.type": 0.1, f"{CLOUDSCAPE}.coverage": 0.7},
    "cumulonimbus, full coverage, wind, no erosion": {f"{CLOUDSCAPE}.type": 1.0, f"{CLOUDSCAPE}.coverage": 0.9,
                                                      f"{CLOUDSCAPE}.erosion": 0.0, f"{CLOUDSCAPE}.wind": [0.4, 0.0, 0.3],
                                                      "time": 3.0},
    "sky light marched through the shell, an edge, octaves": {
        **SHELL, "volumes.0.ambient.visibility": "march", "volumes.0.edge": {"width": 0.3},
        "volumes.0.multiple_scattering": {"octaves": 3}, f"{CLOUDSCAPE}.offset": [0.3, 0.1, 0.7]},
}


def _cloudscape(**overrides):
    return tv.load_scene("cloudscape", {"image.width": 48, "image.height": 48, **overrides})


@pytest.mark.parametrize("name", list(CLOUDSCAPES))
def test_cloudscapes_match_the_eager_march(name):
    """The production clouds in the kernel: their density (the tiled textures, the height profile,
    erosion, coverage), the shell's or the slab's bounds, the graded ambient and the sky blend."""
    kernel, eager = _both(_cloudscape(**CLOUDSCAPES[name]))
    _close(kernel, eager, name)
    assert float(kernel.alpha.max()) > 0.5  # clouds in the picture
    assert kernel.stats["density_evals"] == eager.stats["density_evals"]
    assert kernel.stats["march_steps"] == eager.stats["march_steps"]


def test_cloudscapes_of_other_seeds_give_the_same_bytes_alone_and_in_a_batch():
    scenes = [_cloudscape(), _cloudscape(**{f"{CLOUDSCAPE}.seed": 1, f"{CLOUDSCAPE}.coverage": 0.6}),
              _cloudscape(**{f"{CLOUDSCAPE}.type": 0.3, f"{CLOUDSCAPE}.offset": [0.5, 0.0, 0.2]})]
    kernel, eager = _both(scenes, seed=[1, 2, 3])
    _close(kernel, eager, "a batch of cloudscapes")
    for b, scene in enumerate(scenes):
        alone = tv.render(scene, seed=1 + b, chunk_rays=97)
        assert torch.equal(alone.radiance[0], kernel.radiance[b]) and torch.equal(alone.depth[0], kernel.depth[b])
    assert not torch.equal(kernel.radiance[0], kernel.radiance[1])  # the seed's own textures

LOOK = {**PUFF, "shading": "shader", "shader": {"alpha_scale": 0.3, "light_offset": 0.3, "light_scale": 0.5}}
LOOKS = {
    "the seeds' look, lit by a sun": _media([LOOK]),
    "height-graded ambient, fog, a point light": _media(
        [{**LOOK, "shader": {"ambient": [0.2, 0.3, 0.5], "ambient_top": [0.9, 1.0, 1.1], "fog": 0.05}}],
        lights=[{"kind": "point", "position": [0.5, 1.5, -1.0], "intensity": 4.0}]),
    "no light, the sin dither, size placement, LOD": _media([{**LOOK, "shader": {"light": "none"}}],
                                                         march={"step_size": 0.07, "dither": "sin", "lod": {"scale": 0.5}}),
    "no sky, early stop": {**_media([LOOK], march={"steps": 24, "min_transmittance": 0.1}), "sky": None},
    "lit as a surface, forward differences, a point light": _media(
        [{**PUFF, "shading": "surface", "surface": {"gradient": "forward", "shininess": 20.0, "ambient": [0.1, 0.1, 0.2]}}],
        lights=[SUN, {"kind": "point", "position": [0.5, 1.5, -1.0], "intensity": 4.0}]),
    "lit as a surface, central differences": _media([{**PUFF, "shading": "surface", "surface": {"epsilon": 0.02}}]),
}


@pytest.mark.parametrize("name", list(LOOKS))
def test_the_seeds_look_matches_its_eager_loop(name):
    kernel, eager = _both(LOOKS[name])
    _close(kernel, eager, name)
    assert kernel.stats["density_evals"] == eager.stats["density_evals"]
    assert kernel.stats["march_steps"] == eager.stats["march_steps"]


@pytest.mark.parametrize("index", [0, 1])
def test_voxel_terrain_samples_march_their_cloud_layer_in_the_kernel(index):
    """voxel-terrain.toml: the seeds' look over voxels (the volume marches up to the terrain)."""
    scene = Recipe.load(CLOUDS.parent / "voxel-terrain.toml", SIZE).sample_with_params(index, 0)[0]
    kernel, eager = _both(scene)
    _close(kernel, eager, f"voxel-terrain sample {index}")


def test_a_joint_member_without_a_kernel_marches_every_member_eagerly():
    # a homogeneous box under an unshadowed sun has a closed form, which the kernel does not mix with marches
    box = {**FOG, "density": {"constant": 1.0}}
    out = tv.render(_media([PUFF, box], lights=[{**SUN, "shadow": None}], march={"steps": 24, "closed_form": True}))
    assert out.stats["plan"]["marches"] == {"volume0": "eager", "volume1": "eager"}
    closed = "in closed form, which the kernel does not mix with marches"
    assert out.stats["plan"]["eager_because"] == {"volume0": f"marched with volume1 ({closed})", "volume1": closed}


def test_the_plan_takes_the_kernel_only_where_it_renders_the_technique():
    for kind in ("value", "perlin", "worley"):  # fbm of every noise in the kernel
        fbm = tv.render(_scene(0, **{"volumes.0.density.fbm": {"noise": kind, "octaves": 3}})).stats["plan"]
        assert fbm["marches"] == {"volume0": "drjit"} and "eager_because" not in fbm, kind
    adaptive = tv.render(_scene(0, **{"march.tolerance": 1e-2})).stats["plan"]
    assert adaptive["marches"] == {"volume0": "eager"}
    assert adaptive["eager_because"] == {"volume0": "the tolerance strategy has no kernel"}
    wide = tv.render(_scene(0), dtype=torch.float64)
    assert wide.stats["plan"]["marches"] == {"volume0": "eager"}  # float64: the reference
    assert "float64" in wide.stats["plan"]["eager_because"]["volume0"]
    fast = tv.render(_scene(0), compile="kernels").stats["plan"]
    assert fast["marches"] == {"volume0": "drjit"} and "eager_because" not in fast


def _template(width=40, height=24, **changes):
    """The template-clouds preset with `changes` at key paths ("volumes.0.shader.fog", list indices as numbers)."""
    scene = tv.preset("template-clouds", width=width, height=height).model_dump()
    for path, value in changes.items():
        *parents, last = path.split(".")
        target = scene
        for key in parents:
            target = target[int(key)] if key.isdigit() else target[key]
        target[last] = value
    return tv.load_scene(scene)


TEMPLATE = {
    "template": {},
    "camera inside the layer": {"camera.eye": [0.3, 0.5, 0.2], "camera.target": [1.0, 0.7, -3.0]},
    "camera level with the layer top": {"camera.eye": [0.0, 2.0, 4.0], "camera.target": [0.0, 2.0, 0.0]},
    "height-graded ambient, no fog": {"volumes.0.shader.ambient_top": [0.9, 0.95, 1.1], "volumes.0.shader.fog": 0.0},
    "no derivative light": {"volumes.0.shader.light": "none"},
    "hash dither, count placement, no LOD": {"march.dither": "hash", "march.placement": "count", "march.steps": 24,
                                             "march.lod": None},
    "no density": {"volumes.0.density.clouds.bias": -9.0},
    "opaque: every sample at density 1": {"volumes.0.density.clouds.bias": 9.0, "march.min_transmittance": 0.0},
    "step limit truncates": {"march.steps": 6},
    "two scenes' textures, times and looks": {},  # rendered as a batch of two
}
# the template against its eager march: the same samples (the sample point rounded once, as eager's
# addcmul; a count step divided exactly, `ops.lanes.divide`), so the texture's 8-bit filter and the
# LOD see the same coordinates; left are Dr.Jit's exp in the fog and the order of a few sums.
# Measured over these variants and at 640×360: at most 4.2e-7 on the image, alpha and depth
# bitwise (with the point rounded twice, 1.7e-3 at a few pixels: the filter's 1/255 steps)
TEMPLATE_TOL = 1e-5


def _template_scenes(name):
    if name != "two scenes' textures, times and looks":
        return _template(**TEMPLATE[name])
    return [_template(), _template(time=3.5, **{"volumes.0.density.clouds.texture_seed": 7,
                                                 "volumes.0.density.clouds.wind": [0.2, 0.0, 0.5],
                                                 "lights.0.direction": [0.3, 0.4, -0.8],
                                                 "volumes.0.shader.alpha_scale": 0.6})]


@pytest.mark.parametrize("name", list(TEMPLATE))
def test_the_template_matches_its_eager_march(name):
    """template-clouds (the clouds density's lanes, `fields.clouds.clouds_density`, in the shader
    look) against the eager generic march: the same samples and density evaluations, every output
    within `TEMPLATE_TOL` (depth relative)."""
    kernel, eager = _both(_template_scenes(name))
    for key in ("image", "radiance", "alpha", "depth"):
        a, b = getattr(kernel, key), getattr(eager, key)
        scale = max(1.0, float(b.abs().max())) if key == "depth" else 1.0
        assert float((a - b).abs().max()) <= TEMPLATE_TOL * scale, f"{name}: {key} off by {float((a - b).abs().max()):.3g}"
    assert kernel.stats["march_steps"] == eager.stats["march_steps"], name
    assert kernel.stats["density_evals"] == eager.stats["density_evals"], name


def test_the_template_gives_the_same_bytes_alone_in_a_batch_for_any_chunking_and_thread_count():
    from torchvol.runtime.threads import torch_threads

    scenes = _template_scenes("two scenes' textures, times and looks")
    with torch_threads(1):
        alone = [tv.render(s, chunk_rays=211) for s in scenes]
    with torch_threads(2):
        batch = tv.render(scenes)
    for i, one in enumerate(alone):
        for key in ("image", "depth", "alpha"):
            assert torch.equal(getattr(batch, key)[i], getattr(one, key)[0]), f"scene {i}: {key}"
    assert not torch.equal(batch.image[0], batch.image[1])


def test_a_render_of_kernels_runs_torch_on_one_thread_and_the_kernel_on_the_callers(monkeypatch):
    """Every march is the Dr.Jit kernel: torch's ops are glue (rays, compositing, post), run on one
    thread; the kernel gets the caller's count (`threads.glue_on_one_thread`)."""
    import drjit as dr

    from torchvol.runtime.threads import torch_threads
    from torchvol.volume import kernel_march

    seen = []
    march_look = kernel_march.march_look

    def recording(*args, **kwargs):
        result = march_look(*args, **kwargs)
        seen.append((torch.get_num_threads(), dr.thread_count()))
        return result

    monkeypatch.setattr(kernel_march, "march_look", recording)
    with torch_threads(2):
        tv.render(_template(12, 8))
        assert torch.get_num_threads() == 2
    assert seen and set(seen) == {(1, 2)}


def test_dr_jit_is_available_for_float32_on_the_cpu_only():
    assert drjit_available() and drjit_available(torch.float32, "cpu")
    assert not drjit_available(torch.float64)


def _hard_points():
    """[80,004, 3] float32 points from |p| ≤ 2 to 5·10⁷, past the float->int32 overflow, and NaN."""
    g = torch.Generator().manual_seed(1)
    return torch.cat([(torch.rand(20000, 3, generator=g) - 0.5) * scale for scale in (4.0, 400.0, 1e5, 1e8)]
                     + [torch.tensor([[float("nan"), 0, 0], [1e30, 1, 2], [-1e30, 1, 2], [0.5, 0.5, 1e7]])])


def _jit(t: torch.Tensor):
    from drjit.llvm import Float, Int32

    return (Int32 if t.dtype in (torch.int32, torch.int64) else Float)(t.to(torch.int32 if not t.is_floating_point() else
                                                                            torch.float32).contiguous().numpy())


def _back(v) -> torch.Tensor:
    import numpy as np

    return torch.from_numpy(np.array(v))


def _packed(seeds):
    from torchvol.noise import lattice as noise

    return noise.packed_table(torch.cat([noise.texture_table(noise.default_noise_texture(s)) for s in seeds]))


def test_the_templates_texture_noise_and_fbm_are_the_torch_ones_bitwise():
    """`noise.texture_noise_coords` and `fields.clouds.cloud_fbm` traced by Dr.Jit (one source,
    `ops.lanes`) give their torch values bitwise: past the float->int32 overflow and at NaN, each
    point on its own texture of a stacked table, with the LOD's octaves kept by count."""
    from torchvol.fields import clouds
    from torchvol.noise import lattice as noise

    packed, p = _packed([0, 5]), _hard_points()
    base = ((torch.arange(p.shape[0]) % 2) * 65536).to(torch.int32)
    expected = noise.texture_noise_coords(*p.unbind(1), packed, base)
    got = _back(noise.texture_noise_coords(*(_jit(c) for c in p.unbind(1)), _jit(packed), _jit(base)))
    same = (got == expected) | (got.isnan() & expected.isnan())
    assert same.all(), f"{int((~same).sum())} of {len(p)} differ, first at {p[~same][0].tolist()}"
    g = torch.Generator().manual_seed(3)
    p = (torch.rand(30000, 3, generator=g) - 0.5) * 40.0
    count = torch.randint(1, 6, (p.shape[0],), generator=g, dtype=torch.int32)
    scales = noise.folded_scales(5, dtype=torch.float32, device="cpu")
    from drjit.llvm import Float

    for kept in (None, count):
        expected = clouds.cloud_fbm(*p.unbind(1), packed, base[:p.shape[0]], kept, octaves=5, scales=scales)
        got = clouds.cloud_fbm(*(_jit(c) for c in p.unbind(1)), _jit(packed), _jit(base[:p.shape[0]]),
                               None if kept is None else _jit(kept), octaves=5, scales=[Float(float(c)) for c in scales])
        assert torch.equal(_back(got), expected), f"octaves kept {'all' if kept is None else 'by count'}"


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-3e9, 3e9, allow_nan=False, width=32), min_size=3, max_size=3))
def test_the_templates_texture_noise_is_bitwise_at_any_float32_point(xyz):
    from torchvol.noise import lattice as noise

    packed, p = _packed([3]), torch.tensor([xyz], dtype=torch.float32)
    got = noise.texture_noise_coords(*(_jit(c) for c in p.unbind(1)), _jit(packed), _jit(torch.zeros(1, dtype=torch.int32)))
    assert torch.equal(_back(got), noise.texture_noise_coords(*p.unbind(1), packed))


def _child_render(queue):
    torch.set_num_threads(1)  # as a DataLoader worker does: torch's OpenMP pool does not survive a fork
    out = tv.render(_template(8, 6))
    queue.put((out.stats["plan"]["marches"], out.radiance.numpy().tobytes()))  # bytes: no shared memory to hand over


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork")
def test_a_child_forked_after_drjit_started_renders_with_it_the_same_bytes():
    """A DataLoader worker's default start is a fork: a child forked after its parent started
    Dr.Jit runs the kernels too, and gives the parent's bytes (a sample's bytes must not depend
    on the worker count)."""
    import multiprocessing

    parent = tv.render(_template(8, 6))  # Dr.Jit started in this process
    assert parent.stats["plan"]["marches"] == {"volume0": "drjit"}
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_child_render, args=(queue,))
    child.start()
    marches, radiance = queue.get(timeout=60)
    child.join(60)
    assert child.exitcode == 0
    assert marches == {"volume0": "drjit"} and radiance == parent.radiance.numpy().tobytes()
