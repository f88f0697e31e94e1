"""Mixed recipes: each sample draws which recipe (family) it comes from, so one dataset spans them.

    [dataset]                       # the mixture's outputs (the families' own [dataset] tables are ignored)
    aovs = []

    [image]                         # any scene key here applies to every family, as --set does
    width = 64
    height = 64

    [[families]]
    recipe = "clouds"               # clouds.toml beside this file (or a path relative to it)
    weight = 2.0                    # optional (1); the share of samples drawn from this family
    name = "clouds"                 # optional (the file's stem); params["family"] of its samples
    set = { "volumes[0].phase" = { choice = ["isotropic", { mie = { g = 0.8 } }] } }   # optional overrides

Sample `index` draws its family from a generator seeded by (seed, index, "family"), then is that
family's sample `index` (its own draws, by its own key paths); `params` holds `"family"` and the
family's draws. Samples of different families differ in structure: `datasets.render_samples` renders
each structure as its own batch, so a sample's bytes do not depend on the others in its batch.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from ..schema.validate import SceneError, did_you_mean, fail, finite, known_keys
from .distributions import DIST_KINDS, Dist, check_index
from .recipe import RECIPE_FORMS, Recipe

BUNDLED = Path(__file__).resolve().parents[2] / "datasets"
FAMILY_KEYS = ("recipe", "weight", "name", "set")


def _flatten(node: Mapping, prefix: str = "") -> dict[str, Any]:
    """Scene tables as overrides: {"image.width": 64, ...} (lists and distributions are leaves)."""
    out: dict[str, Any] = {}
    for key, value in node.items():
        path = f"{prefix}.{key}" if prefix else str(key)
        if isinstance(value, Mapping) and value and not (len(value) == 1 and next(iter(value)) in DIST_KINDS):
            out.update(_flatten(value, path))
        else:
            out[path] = value
    return out


def _member_path(where: str, spec: Any, base: Path) -> Path:
    if not isinstance(spec, str) or not spec:
        fail(where, spec, "expected a recipe file name, e.g. 'clouds' or 'clouds.toml' (beside the mixed recipe)")
    path = Path(spec) if spec.endswith(".toml") else Path(f"{spec}.toml")
    for root in (base, BUNDLED):
        if (root / path).is_file():
            return root / path
    fail(where, spec, f"no such recipe in {base}" + (f" or {BUNDLED}" if base != BUNDLED else "") + did_you_mean(
        path.stem, [p.stem for p in base.glob("*.toml")]))


@dataclass(frozen=True)
class MixedRecipe(Recipe):
    """A recipe whose samples come from its `members` (name -> Recipe); `dists["family"]` picks one."""

    members: Mapping[str, Recipe] | None = None
    base: Path = BUNDLED  # where family recipe names are looked up first

    @classmethod
    def build(cls, data: dict, meta: Mapping, *, raw: dict, aovs: tuple[str, ...], name: str,
              source: Any) -> "MixedRecipe":
        """`data`: the recipe's tables without [dataset], `meta` its [dataset]; `raw` its source (for
        meta.json); `source` what Recipe.load was given (a file: families are looked up beside it)."""
        for key in meta:
            if key != "aovs":
                fail(f"dataset.{key}", meta[key], "a mixed recipe ([[families]]) takes only dataset.aovs")
        if isinstance(source, MixedRecipe):
            base = source.base
        elif isinstance(source, (str, Path)) and Path(source).is_file():
            base = Path(source).resolve().parent
        else:
            base = BUNDLED
        families = data.pop("families")
        if not isinstance(families, list) or not families:
            fail("families", families, "expected a non-empty list of tables [[families]] recipe = \"clouds\"")
        common = _flatten(data)
        members: dict[str, Recipe] = {}
        weights: list[float] = []
        for k, family in enumerate(families):
            where = f"families[{k}]"
            if not isinstance(family, Mapping):
                fail(where, family, "expected a table { recipe = \"clouds\", weight = 1.0 }")
            known_keys(where, family, FAMILY_KEYS)
            if "recipe" not in family:
                fail(where, family, "a family needs recipe = \"NAME\" (a recipe file)")
            path = _member_path(f"{where}.recipe", family["recipe"], base)
            label = family.get("name", path.stem)
            if not isinstance(label, str) or not label:
                fail(f"{where}.name", label, "expected a non-empty string")
            if label in members:
                fail(f"{where}.name", label, "family names must be distinct (give each a name)")
            weights.append(finite(f"{where}.weight", family.get("weight", 1.0), low=0.0))
            extra = family.get("set", {})
            if not isinstance(extra, Mapping):
                fail(f"{where}.set", extra, "expected a table of key paths to values, e.g. { \"march.steps\" = 16 }")
            try:
                member = Recipe.load(path, {**common, **extra})
            except SceneError as err:
                raise SceneError(f"{where} ({path.name}): {err.path}", err.value, err.allowed) from None
            if isinstance(member, MixedRecipe):
                fail(f"{where}.recipe", family["recipe"], "a mixed recipe cannot be a family of another")
            members[label] = member
        if sum(weights) <= 0:
            fail("families", weights, "expected weights >= 0, not all 0")
        family = Dist("family", "choice", (list(members), weights, [{} for _ in members]))
        return cls(template={}, dists={"family": family}, aovs=aovs, name=name, source=raw,
                   members=members, base=base)

    def sample_params(self, index: int, seed: int = 0) -> dict[str, Any]:
        """Sample `index`'s `family` and that family's drawn values {key path: value}."""
        check_index(index, seed)
        family = self.dists["family"].draw(seed, index)
        return {"family": family, **self.members[family].sample_params(index, seed)}

    def sample_with_params(self, index: int, seed: int = 0):
        """The scene of sample `index` (its family's) and its `sample_params`."""
        params = self.sample_params(index, seed)
        drawn = {k: v for k, v in params.items() if k != "family"}
        return self.members[params["family"]]._scene(drawn), params

    def describe(self) -> dict:
        """The mixture and each family's recipe as it was loaded (a changed family file changes meta.json)."""
        out = super().describe()
        out["family_recipes"] = {label: json.loads(json.dumps(m.describe())) for label, m in self.members.items()}
        return out


RECIPE_FORMS["families"] = MixedRecipe.build
