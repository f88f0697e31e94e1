"""The physical march as one Dr.Jit kernel (`torchvol.volume.kernel_march`): held to the eager
march (the reference, `compile="off"`) within the tolerance table on the recipe that uses it and
on every variant it renders; its bytes the same alone and in a batch, for any chunking and thread
count; the plan taking it by default where it renders the technique and eager elsewhere."""

from pathlib import Path

import pytest
import torch
from conftest import TOL

import torchvol as tv
from torchvol.dataset.recipe import Recipe
from torchvol.volume import drjit_march

pytestmark = pytest.mark.skipif(not drjit_march.available(torch.zeros(1)), reason="Dr.Jit's LLVM backend is not available")
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


@pytest.mark.parametrize("hash_", ["arithmetic", "table"])
def test_the_same_bytes_alone_in_a_batch_for_any_chunking_and_thread_count(hash_):
    scenes = [_scene(i, **{"volumes.0.density.fbm.hash": hash_}) for i in range(3)]
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


SUN = {"kind": "sun", "direction": [0.3, 0.9, 0.2], "intensity": 5.0, "shadow": {"steps": 4}}
PUFF = {"bounds": {"sphere": {"center": [0.0, 0.0, 0.0], "radius": 1.0}}, "sigma_t": 6.0, "albedo": 0.9,
        "density": {"fbm": {"octaves": 3, "frequency": 2.0, "seed": 4, "bias": 0.1}}, "phase": {"hg": {"g": 0.5}}}
FOG = {"bounds": {"box": {"min": [-2.0, -1.5, -2.0], "max": [2.0, 0.3, 2.0]}}, "sigma_t": 0.8, "albedo": 0.8,
       "density": {"exponential": {"value": 1.0, "base": -1.5, "scale_height": 0.6}}}


def _media(volumes, lights=(SUN,), **extra):
    return {"image": {"width": 24, "height": 20}, "camera": {"eye": [0.3, 0.6, -3.5], "target": [0.0, 0.0, 0.0], "fov_y": 50.0},
            "sky": {"kind": "constant", "radiance": [0.3, 0.4, 0.6]}, "lights": list(lights), "volumes": list(volumes),
            "march": {"steps": 24}, **extra}


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


def test_the_joint_kernel_gives_the_same_bytes_alone_in_a_batch_and_for_any_chunking():
    scenes = [JOINT["a cloud in fog"], _media([{**PUFF, "sigma_t": 3.0, "density": {"fbm": {"octaves": 3, "seed": 9}}},
                                               {**FOG, "sigma_t": 0.3}], lights=[{**SUN, "direction": [-0.4, 0.8, 0.1]}])]
    batch = tv.render(scenes, seed=[1, 2])
    for b, scene in enumerate(scenes):
        alone = tv.render(scene, seed=1 + b, chunk_rays=53)
        assert torch.equal(alone.radiance[0], batch.radiance[b]) and torch.equal(alone.depth[0], batch.depth[b])


def _particles(seed: int, combine: str):
    return {**PUFF, "bounds": {"box": {"min": [-1.5, -1.2, -1.2], "max": [1.5, 1.2, 1.2]}},
            "density": {"particles": {"count": 7, "seed": seed, "region_min": [-0.8, -0.5, -0.5], "region_max": [0.8, 0.5, 0.5],
                                      "radius": [0.3, 0.6], "core": -0.2, "amplitude": 2.0, "octaves": 3, "combine": combine}}}


@pytest.mark.parametrize("combine", ["sum", "max"])
def test_particles_match_eager_and_give_the_same_bytes_alone_and_in_a_batch(combine):
    scenes = [_media([_particles(seed, combine)]) for seed in (3, 4)]
    for scene in scenes:
        kernel, eager = _both(scene)
        _close(kernel, eager, f"particles, {combine}")
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
    perlin = {**FOG, "density": {"fbm": {"noise": "perlin", "octaves": 2}}}
    out = tv.render(_media([PUFF, perlin], lights=[{**SUN, "shadow": None}]))
    assert out.stats["plan"]["marches"] == {"volume0": "eager", "volume1": "eager"}
    assert out.stats["plan"]["eager_because"] == {"volume0": "marched with volume1 (no kernel for the fbm density)",
                                                  "volume1": "no kernel for the fbm density"}
    # a shadow ray through it: the other volume's own march has no kernel either
    shadowed = tv.render(_media([PUFF, perlin])).stats["plan"]["eager_because"]
    assert shadowed["volume0"] == "no kernel for shadows through a volume not written in lanes"


def test_the_plan_takes_the_kernel_only_where_it_renders_the_technique():
    perlin = tv.render(_scene(0, **{"volumes.0.density.fbm": {"noise": "perlin", "octaves": 3}}))
    assert perlin.stats["plan"]["marches"] == {"volume0": "eager"}  # Perlin's gradient noise has no kernel yet
    assert perlin.stats["plan"]["eager_because"] == {"volume0": "no kernel for the fbm density"}
    wide = tv.render(_scene(0), dtype=torch.float64)
    assert wide.stats["plan"]["marches"] == {"volume0": "eager"}  # float64: the reference
    assert "float64" in wide.stats["plan"]["eager_because"]["volume0"]
    fast = tv.render(_scene(0), compile="kernels").stats["plan"]
    assert fast["marches"] == {"volume0": "drjit"} and "eager_because" not in fast
