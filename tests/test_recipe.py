"""Recipes: distributions validated with key paths; samples deterministic per (seed, index)."""

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import torchvol as tv
from torchvol.dataset.recipe import Recipe

ROOT = Path(__file__).resolve().parents[1]
TINY = {"image.width": 16, "image.height": 12, "march.steps": 4}

RANDOM = {
    "volumes[0].sigma_t": {"uniform": [5, 20]},
    "volumes[0].albedo": {"normal": {"mean": 0.9, "std": 0.5, "min": 0.5, "max": 1.0}},
    "volumes[0].density.fbm.frequency": {"loguniform": [1, 8]},
    "volumes[0].density.fbm.seed": {"integer": [3, 5]},
    "volumes[0].density.fbm.offset": {"uniform": [[0, 0, 0], [1, 2, 3]]},
    "lights[0].direction": {"hemisphere": {"elevation": [10, 60], "azimuth": [0, 90]}},
    "camera.eye": {"orbit": {"center": [0, 0, 0], "distance": [3, 4], "elevation": [0, 30]}},
    "sky.radiance": {"choice": {"values": [[0.1, 0.1, 0.1], [0.2, 0.3, 0.4]], "weights": [1, 3]}},
}


def recipe(**extra):
    return Recipe.load("cloud-puff", {**TINY, **RANDOM, **extra})


def test_samples_are_deterministic_and_independent_across_indices():
    r = recipe()
    assert r.sample_params(3, seed=7) == r.sample_params(3, seed=7)
    assert r.sample_params(3, seed=7) != r.sample_params(4, seed=7) != r.sample_params(3, seed=8)
    scene, params = r.sample_with_params(3, seed=7)
    assert scene == r.sample(3, seed=7) and scene.volumes[0].sigma_t == params["volumes[0].sigma_t"]
    assert json.loads(json.dumps(params)) == params
    # a key's draws do not depend on the other random keys
    alone = Recipe.load("cloud-puff", {**TINY, "volumes[0].sigma_t": {"uniform": [5, 20]}})
    assert alone.sample_params(3, seed=7)["volumes[0].sigma_t"] == params["volumes[0].sigma_t"]


def test_draws_are_the_same_in_another_process():
    code = ("import json; from torchvol.dataset.recipe import Recipe; import tests.test_recipe as t; "
            "print(json.dumps([t.recipe().sample_params(i, seed=5) for i in (9, 2)]))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    r = recipe()
    assert json.loads(done.stdout) == [r.sample_params(i, seed=5) for i in (9, 2)]


def test_draws_respect_their_ranges():
    r = recipe()
    draws = [r.sample_params(i, seed=1) for i in range(200)]
    for p in draws:
        assert 5 <= p["volumes[0].sigma_t"] <= 20 and 0.5 <= p["volumes[0].albedo"] <= 1.0
        assert 1 <= p["volumes[0].density.fbm.frequency"] <= 8 and p["volumes[0].density.fbm.seed"] in (3, 4, 5)
        assert all(0 <= x <= hi for x, hi in zip(p["volumes[0].density.fbm.offset"], (1, 2, 3)))
        x, y, z = p["lights[0].direction"]
        assert math.isclose(x * x + y * y + z * z, 1.0) and 10 - 1e-9 <= math.degrees(math.asin(y)) <= 60 + 1e-9
        assert x >= -1e-12 and z >= -1e-12  # azimuth in [0, 90]: from +z towards +x
        assert 3 - 1e-9 <= math.dist(p["camera.eye"], (0, 0, 0)) <= 4 + 1e-9 and p["camera.eye"][1] >= -1e-9
    assert {p["volumes[0].density.fbm.seed"] for p in draws} == {3, 4, 5}
    heavy = sum(p["sky.radiance"] == [0.2, 0.3, 0.4] for p in draws)
    assert 120 < heavy < 180  # weights 1:3
    assert any(p["volumes[0].albedo"] == 1.0 for p in draws)  # the normal is clipped


@pytest.mark.parametrize(
    "overrides,needle",
    [
        ({"volumes[0].sigma_t": {"uniform": [-5, 20]}}, "volumes[0].sigma_t: got {'uniform': [-5, 20]}; the distribution can give -5.0"),
        ({"volumes[0].sigma_t": {"uniform": [20, 5]}}, "volumes[0].sigma_t.uniform"),
        ({"volumes[0].sigma_t": {"uniform": [5, float("nan")]}}, "volumes[0].sigma_t.uniform[1]: got nan"),
        ({"volumes[0].sigma_t": {"loguniform": [0, 5]}}, "loguniform bounds must be > 0"),
        ({"volumes[0].sigma_t": {"unifrom": [5, 6]}}, "did you mean 'uniform'"),
        ({"volumes[0].albedo": {"normal": {"mean": 0.5, "sdt": 1}}}, "volumes[0].albedo.normal.sdt"),
        ({"volumes[0].albedo": {"normal": {"mean": 0.5, "std": 0.1}}}, "volumes[0].albedo"),  # unclipped: can exceed 1
        ({"volumes[0].density.fbm.seed": {"integer": [0.5, 3]}}, "volumes[0].density.fbm.seed.integer"),
        ({"volumes[0].phase": {"choice": []}}, "volumes[0].phase.choice"),
        ({"volumes[0].phase": {"choice": ["isotropic", "nope"]}}, "volumes[0].phase"),
        ({"lights[0].direction": {"hemisphere": {"elevation": [10, 100]}}}, "lights[0].direction.hemisphere.elevation"),
        ({"camera.eye": {"orbit": {"distance": [3, 4], "centre": [0, 0, 0]}}}, "did you mean 'center'"),
        ({"camera.eye": {"orbit": {"elevation": [0, 10]}}}, "orbit needs distance"),
        ({"camera.fov": {"uniform": [30, 40]}}, "did you mean 'fov_y'"),
        ({"dataset.aovs": ["nope"]}, "dataset.aovs"),
    ],
)
def test_bad_recipes_name_the_key_path(overrides, needle):
    with pytest.raises(ValueError) as err:
        Recipe.load("cloud-puff", overrides)
    assert needle in str(err.value)


def test_bad_sample_arguments():
    with pytest.raises(ValueError, match="index"):
        recipe().sample(-1)
    with pytest.raises(ValueError, match="seed"):
        recipe().sample(0, seed="x")


@pytest.mark.parametrize("name", sorted(p.stem for p in (ROOT / "datasets").glob("*.toml")))
def test_bundled_recipes_sample_and_render(name):
    """Every bundled recipe draws distinct scenes that render finite, as the generator renders them
    (one batch per structure: e.g. a particle count splits them)."""
    r = Recipe.load(ROOT / "datasets" / f"{name}.toml", TINY)
    assert r.dists
    assert len({r.sample(i, seed=0).model_dump_json() for i in range(3)}) == 3
    samples = tv.SceneDataset(r, 3).batch([0, 1, 2])
    for s in samples:
        assert s["image"].shape == (r.views * (r.sequence.frames if r.sequence else 1),) * (r.views > 1 or r.sequence is not None) + (3, 12, 16) and torch.isfinite(s["image"]).all() and torch.isfinite(s["depth"]).all()
        assert torch.isfinite(s["alpha"]).all() and all(torch.isfinite(s[a]).all() for a in r.aovs)
        assert set(r.aovs) <= set(s)


def _techniques(scene) -> set[str]:
    """The techniques a scene uses, by registry family: `family:name` (see docs/DATASETS.md)."""
    out = {f"light:{l.kind}" for l in scene.lights} | {f"tonemap:{scene.post.tonemap}"}
    out |= {f"post:{k}" for k in ("fog", "god_rays") if getattr(scene.post, k) is not None}
    out |= {"post:vignette"} if scene.post.vignette > 0 else set()
    out |= {f"sky:{scene.sky.kind}"} if scene.sky is not None else set()
    out |= {f"image:{k}" for k in ("spp", "passes") if (getattr(scene.image, k) or 1) > 1}
    out |= {"terrain"} if scene.terrain is not None else set()
    out |= {"atmosphere"} if scene.atmosphere is not None else set()
    for v in scene.volumes:
        out |= {f"bounds:{v.bounds.kind}", f"density:{v.density.kind}", f"phase:{v.phase.kind}", f"shading:{v.shading}"}
        out |= {f"emission_map:{v.emission_map.kind}"} if v.emission_map is not None else set()
    if scene.voxels is not None:
        vox = scene.voxels
        out |= {f"voxels:{vox.occupancy.kind}", f"voxels:{vox.traversal}"}
        out |= {f"voxels:{k}" for k in ("ao", "shadow", "reflections", "glow", "rounded", "fog", "water", "gi")
                if getattr(vox, k) is not None}
    return out


def test_every_technique_is_reachable_from_a_bundled_recipe():
    """The registries' kinds (and the voxel and post variants) each appear in some bundled recipe's
    draws: the audit table of docs/DATASETS.md."""
    from torchvol.fields import DENSITIES
    from torchvol.geometry.bounds import BOUNDS
    from torchvol.light.lights import LIGHTS
    from torchvol.light.phase import PHASES
    from torchvol.light.sky import SKIES
    from torchvol.volume.emission import EMISSION_MAPS
    from torchvol.volume.shading import SHADINGS

    seen: set[str] = set()
    for path in sorted((ROOT / "datasets").glob("*.toml")):
        r = Recipe.load(path, TINY)
        for i in range(24):
            seen |= _techniques(r.sample(i, seed=0))
    wanted = {f"{family}:{name}" for family, registry in (
        ("bounds", BOUNDS), ("density", DENSITIES), ("phase", PHASES), ("light", LIGHTS), ("sky", SKIES),
        ("shading", SHADINGS), ("emission_map", EMISSION_MAPS)) for name in registry.names()}
    wanted |= {f"tonemap:{t}" for t in ("none", "smoothstep", "reinhard", "aces")}
    wanted |= {"post:fog", "post:god_rays", "post:vignette", "terrain", "atmosphere", "voxels:sdf", "voxels:terrain",
               "voxels:hybrid", "voxels:ao", "voxels:shadow", "voxels:reflections", "voxels:glow", "voxels:rounded",
               "voxels:fog", "voxels:water", "voxels:gi", "image:spp", "image:passes"}
    # not asked for: grid and function occupancies and texture atlases need arrays, callables or image
    # files, and march.tolerance is an accuracy mode (docs/DATASETS.md, "technique → recipe")
    assert wanted - seen == set()


def test_recipe_from_toml_with_override_distribution(tmp_path):
    path = tmp_path / "r.toml"
    path.write_text('[image]\nwidth = 8\nheight = 6\n[[volumes]]\nsigma_t = { uniform = [1, 2] }\n')
    r = Recipe.load(path, {"volumes[0].albedo": {"uniform": [0.2, 0.4]}})
    assert set(r.sample_params(0)) == {"volumes[0].sigma_t", "volumes[0].albedo"}
    assert Recipe.load(r) is r


@pytest.mark.parametrize("path", sorted(Path("datasets").glob("*.toml")), ids=lambda p: p.stem)
def test_a_sample_copies_the_template_without_its_tables(path):
    """A sample copies the template's skeleton (None where a distribution sits, every one then set),
    not the whole template: the same scene as setting its values into a deep copy of the template,
    and the template untouched."""
    import copy

    from torchvol.scene.model import validate_scene
    from torchvol.schema.keypath import copy_plain, set_path

    recipe = Recipe.load(path)
    if type(recipe) is not Recipe:
        pytest.skip("another recipe form (its families are recipes of their own)")
    before = copy.deepcopy(recipe.template)
    for index in range(3):
        params = recipe.sample_params(index, seed=5)
        data = copy.deepcopy(recipe.template)
        for key, value in params.items():
            set_path(data, key, value)
        assert recipe.sample(index, seed=5) == validate_scene(data), f"sample {index}"
    assert recipe.template == before
    plain = copy_plain(before)
    assert plain == before
    plain["image"]["width"] = -1
    assert before["image"]["width"] != -1, "copy_plain shared a table"
