"""Mixed recipes (torchvol/mix.py) and draws inside a choice: samples draw their structure, render
grouped by structure, and keep their bytes whatever their batch."""

import json
from pathlib import Path

import pytest
import torch

from torchvol.dataset.codec import encode_sample
from torchvol.dataset.datasets import render_samples
from torchvol.dataset.generate import generate
from torchvol.dataset.mix import MixedRecipe
from torchvol.dataset.recipe import Recipe
from torchvol.scene.quality import at_level
from torchvol.schema.batch import structure_key

ROOT = Path(__file__).resolve().parents[1]
MIXED = ROOT / "datasets" / "mixed.toml"
TINY = {"image.width": 8, "image.height": 8, "march.steps": 4}


def test_mixed_draws_span_every_family():
    r = Recipe.load(MIXED, TINY)
    assert isinstance(r, MixedRecipe)
    families = [f.get("name", Path(f["recipe"]).stem) for f in r.source["families"]]
    drawn = [r.sample_params(i, seed=0) for i in range(256)]
    assert {p["family"] for p in drawn} == set(families) == set(r.members)
    assert len(families) >= 15
    # a sample is its family's sample at the same (seed, index), with the mixture's keys applied
    for i in (0, 1, 2, 3):
        p = drawn[i]
        member = Recipe.load(ROOT / "datasets" / f"{p['family']}.toml", TINY) if p["family"] != "voxel-fog" else None
        if member is not None and p["family"] != "clouds":
            assert {k: v for k, v in p.items() if k != "family"} == member.sample_params(i, seed=0)
        scene, again = r.sample_with_params(i, seed=0)
        assert again == p and json.loads(json.dumps(p)) == p
        assert (scene.image.width, scene.image.height) == (8, 8)
    # the family decides the structure: phases, skies, volume counts and surfaces all vary (with
    # margin: a family added to mixed.toml changes which family an index draws)
    scenes = [r.sample(i) for i in range(128)]
    assert {len(s.volumes) for s in scenes} >= {0, 1, 2}
    assert {s.voxels is not None for s in scenes} == {True, False} and any(s.terrain is not None for s in scenes)
    assert len({v.phase.kind for s in scenes for v in s.volumes}) >= 4
    assert len({s.sky.kind for s in scenes if s.sky is not None}) >= 2


def test_mixed_samples_render_grouped_by_structure_and_keep_their_bytes(tmp_path):
    r = Recipe.load(MIXED, TINY)
    indices = list(range(6))
    keys = {structure_key(at_level(r.sample(i))) for i in indices}
    assert len(keys) > 1  # several structures in one call
    together = render_samples(r, indices)
    assert [s["index"] for s in together] == indices
    for s in together:
        alone = render_samples(r, [s["index"]])[0]
        assert encode_sample(s, ()) == encode_sample(alone, ())
        assert s["params"] == alone["params"]
    done = generate(MIXED, count=6, out=tmp_path / "mixed", batch=4, overrides=TINY, progress=False)
    assert done["finished"] and done["written"] == 6
    for s in together:
        stem = tmp_path / "mixed" / "samples" / f"{s['index']:06d}"
        assert Path(f"{stem}.image.png").read_bytes() == encode_sample(s, ())["image.png"]
        assert json.loads(Path(f"{stem}.json").read_text())["params"]["family"] == s["params"]["family"]


def test_choice_values_hold_distributions():
    phase = {"choice": ["isotropic", {"hg": {"g": {"uniform": [0.2, 0.4]}}},
                        {"mie": {"g": {"choice": [0.7, {"uniform": [0.8, 0.9]}]}}}]}
    r = Recipe.load("cloud-puff", {**TINY, "volumes[0].phase": phase})
    seen = set()
    for i in range(80):
        p = r.sample_params(i)["volumes[0].phase"]
        scene = r.sample(i)
        if p == "isotropic":
            seen.add("isotropic")
        elif "hg" in p:
            seen.add("hg")
            assert 0.2 <= p["hg"]["g"] <= 0.4 and scene.volumes[0].phase.hg.g == p["hg"]["g"]
        else:
            seen.add("mie")
            assert p["mie"]["g"] == 0.7 or 0.8 <= p["mie"]["g"] <= 0.9
    assert seen == {"isotropic", "hg", "mie"}
    # a draw inside a value is keyed by its path through the choice: the same in any recipe
    other = Recipe.load("cloud-puff", {**TINY, "volumes[0].phase": phase, "volumes[0].sigma_t": {"uniform": [5, 9]}})
    assert all(other.sample_params(i)["volumes[0].phase"] == r.sample_params(i)["volumes[0].phase"] for i in range(20))
    # lists may be chosen too, empty ones included (zero or one volume)
    one = Recipe.load("cloud-puff", {**TINY, "volumes": {"choice": [[], [{"sigma_t": {"uniform": [1, 2]}}]]}})
    counts = {len(one.sample(i).volumes) for i in range(20)}
    assert counts == {0, 1}


@pytest.mark.parametrize(
    "overrides,needle",
    [
        ({"volumes[0].phase": {"choice": ["isotropic", {"hg": {"g": {"uniform": [0.9, 0.1]}}}]}},
         "volumes[0].phase.choice[1].hg.g.uniform"),
        ({"volumes[0].phase": {"choice": ["isotropic", {"hg": {"g": {"uniform": [0.5, 1.5]}}}]}},
         "volumes[0].phase: got {'choice'"),
        ({"volumes[0].phase": {"choice": [{"hg": {"g": {"unifrom": [0.1, 0.2]}}}]}}, "did you mean 'uniform'"),
    ],
)
def test_bad_draws_inside_a_choice_name_their_path(overrides, needle):
    with pytest.raises(ValueError) as err:
        Recipe.load("cloud-puff", overrides)
    assert needle in str(err.value)


@pytest.mark.parametrize(
    "families,needle",
    [
        ([], "families: got []"),
        ([{"recipe": "clouds", "wieght": 2}], "families[0].wieght: got 2; unknown key (did you mean 'weight'?)"),
        ([{"weight": 2}], "families[0]: got {'weight': 2}; a family needs recipe"),
        ([{"recipe": "no-such-recipe"}], "families[0].recipe: got 'no-such-recipe'; no such recipe"),
        ([{"recipe": "clouds"}, {"recipe": "clouds"}], "families[1].name: got 'clouds'; family names must be distinct"),
        ([{"recipe": "clouds", "weight": -1}], "families[0].weight: got -1"),
        ([{"recipe": "clouds", "weight": 0}], "families: got [0.0]"),
        ([{"recipe": "clouds", "set": {"volumes[0].sigma_t": {"uniform": [-2, 3]}}}],
         "families[0] (clouds.toml): volumes[0].sigma_t: got {'uniform': [-2, 3]}"),
        ([{"recipe": "mixed"}], "families[0].recipe: got 'mixed'; a mixed recipe cannot be a family"),
    ],
)
def test_bad_mixed_recipes_name_the_key_path(families, needle):
    with pytest.raises(ValueError) as err:
        Recipe.load({"image": {"width": 8, "height": 8}, "families": families})
    assert needle in str(err.value)


def test_mixed_recipe_overrides_reach_every_family(tmp_path):
    path = tmp_path / "two.toml"
    path.write_text('[dataset]\naovs = ["radiance"]\n[image]\nwidth = 6\nheight = 4\n'
                    '[[families]]\nrecipe = "media"\nweight = 3\n[[families]]\nrecipe = "fur-ball"\n')
    r = Recipe.load(path, {"image.height": 5})
    assert r.aovs == ("radiance",) and set(r.members) == {"media", "fur-ball"}
    assert all((r.sample(i).image.width, r.sample(i).image.height) == (6, 5) for i in range(8))
    again = Recipe.load(r, {"image.width": 7})  # reloaded with overrides: families still found
    assert isinstance(again, MixedRecipe) and again.sample(0).image.width == 7
    item = render_samples(r, [0])[0]
    assert item["radiance"].shape == (3, 5, 6) and torch.isfinite(item["image"]).all()
