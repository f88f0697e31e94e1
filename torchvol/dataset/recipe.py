"""Recipes: a scene whose values may be distributions; `sample(index, seed)` draws one Scene.

Where a value goes, a recipe may put a distribution (`torchvol.dataset.distributions`: its kinds,
and the seeded draws that make a sample depend only on (seed, index)).

A recipe may carry a `[dataset]` table (not part of the scene): `aovs = ["depth_median", ...]`, the
extra outputs a generated dataset stores; `views = V`, cameras per sample (`views.py`);
`volume_label = { resolution = N }`, the extinction grid label (`volume_label.py`); `frames`,
`dt`, `camera_path`: sequences (`sequence.py`). A recipe with `[[families]]` is a mixture of
whole recipes, one drawn per sample (`mix.py`).
"""

from __future__ import annotations

import copy
import json
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Callable, Mapping

from ..renderer.aovs import AOVS
from ..scene.model import Scene, read_source, validate_scene
from ..schema.keypath import copy_plain, lookup, set_path
from ..schema.validate import SceneError, fail, known_keys
from .distributions import Dist, check_index, find_dists, mix_seed
from .sequence_spec import SequenceSpec, parse_sequence
from .views import parse_dataset
from .volume_label import check_scene

RECIPE_KEYS = ("aovs", "views", "volume_label", "frames", "dt", "camera_path")  # views.py, sequence_spec.py

# Recipe forms other than a scene template, by the top-level key that marks one: each builds its
# Recipe from (data without [dataset], meta = [dataset], *, raw, aovs, name, source). mix.py adds
# "families" (mixed recipes); torchvol.dataset imports mix.py, so the form is there whenever a
# recipe loads, and recipe.py need not import the forms built on it.
RECIPE_FORMS: dict[str, Callable[..., Recipe]] = {}


@dataclass(frozen=True)
class Recipe:
    """A scene template (raw dict) plus the distributions at its key paths (`dists`)."""

    template: dict
    dists: dict[str, Dist]
    aovs: tuple[str, ...] = ()
    name: str = "recipe"
    views: int = 1  # cameras per sample (`views.py`)
    volume_label: int | None = None  # the extinction label's resolution (`volume_label.py`)
    source: dict = field(default_factory=dict, repr=False)
    sequence: SequenceSpec | None = None  # [dataset] frames > 1 (`sequence.py`)

    @classmethod
    def load(cls, source: str | Path | Mapping | "Recipe", overrides: Mapping[str, Any] | None = None) -> "Recipe":
        """A validated recipe from a .toml path, a preset name or a dict; `overrides` maps dotted key
        paths to values or distribution tables (``{"volumes[0].sigma_t": {"uniform": [5, 9]}}``)."""
        if isinstance(source, Recipe):
            if not overrides:
                return source
            name, data = source.name, copy.deepcopy(source.source)
        else:
            name = Path(source).stem if isinstance(source, (str, Path)) else "recipe"
            data = read_source(source)
        for key, value in (overrides or {}).items():
            set_path(data, key, value)
        raw = copy.deepcopy(data)
        meta = data.pop("dataset", None) or {}
        if not isinstance(meta, Mapping):
            fail("dataset", meta, "expected a table { aovs = [...] }")
        known_keys("dataset", meta, RECIPE_KEYS)
        aovs = meta.get("aovs", [])
        if not isinstance(aovs, list) or any(a not in AOVS for a in aovs) or len(set(aovs)) != len(aovs):
            fail("dataset.aovs", aovs, "expected a list of distinct AOV names from: " + ", ".join(AOVS.names()))
        form = next((key for key in RECIPE_FORMS if key in data), None)
        if form is not None:
            return RECIPE_FORMS[form](data, meta, raw=raw, aovs=tuple(aovs), name=name, source=source)
        dists: dict[str, Dist] = {}
        find_dists(data, (), dists)
        views, volume_label = parse_dataset(meta, dists)
        recipe = cls(template=data, dists=dists, aovs=tuple(aovs), name=name, source=raw, views=views,
                     volume_label=volume_label, sequence=parse_sequence(meta))
        recipe._validate()
        if volume_label is not None:  # a label needs bounded volumes: refused at load, not on a sample
            check_scene(recipe.sample(0), volume_label)
        return recipe

    def _validate(self) -> None:
        """Validate the scene at every distribution's extremes (and each choice), so a bad range
        fails at load with its key path rather than on some later sample."""
        corners = {p: d.corners() for p, d in self.dists.items()}
        rounds = max((len(c) for c in corners.values()), default=1)
        for r in range(rounds):
            values = {p: c[r % len(c)] for p, c in corners.items()}
            try:
                self._scene(values)
            except SceneError as err:
                owner = next((p for p in self.dists if err.path == p or err.path.startswith(p + ".")
                              or err.path.startswith(p + "[") or p.startswith(err.path + ".")
                              or p.startswith(err.path + "[")), None)
                if owner is None:
                    raise
                raw = lookup(self.template, owner)
                fail(owner, raw, f"the distribution can give {values[owner]!r}, which is invalid: "
                     f"{err.path}: {err.allowed}")

    @cached_property
    def _skeleton(self) -> dict:
        """The template without its distributions' tables (None at their key paths): what a sample
        copies before setting every one of them (the tables, a choice's alternatives above all,
        were most of a copy of the template)."""
        skeleton = copy.deepcopy(self.template)
        for path in self.dists:
            set_path(skeleton, path, None)
        return skeleton

    def _scene(self, values: Mapping[str, Any]) -> Scene:
        data = copy_plain(self._skeleton if values.keys() == self.dists.keys() else self.template)
        for path, value in values.items():
            set_path(data, path, value)
        return validate_scene(data)

    def sample_params(self, index: int, seed: int = 0) -> dict[str, Any]:
        """The values drawn for sample `index`: {key path: value}, JSON-serialisable."""
        check_index(index, seed)
        return {path: dist.draw(seed, index) for path, dist in self.dists.items()}

    def sample_with_params(self, index: int, seed: int = 0) -> tuple[Scene, dict[str, Any]]:
        """The scene of sample `index` and the values drawn for it (`sample_params`)."""
        params = self.sample_params(index, seed)
        return self._scene(params), params

    def sample(self, index: int, seed: int = 0) -> Scene:
        """The scene of sample `index`: deterministic per (seed, index), independent across indices."""
        return self.sample_with_params(index, seed)[0]

    def describe(self) -> dict:
        """The recipe as JSON-safe data (for meta.json): the raw tables, arrays as their shapes."""
        return json.loads(json.dumps(self.source, default=lambda o: f"<{type(o).__name__} {getattr(o, 'shape', '')}>"))


def render_seed(index: int, seed: int) -> int:
    """The renderer's per-sample seed (dither, sub-pixel jitter) for sample `index`."""
    return mix_seed("torchvol.render", int(seed), int(index)) % 2**31
