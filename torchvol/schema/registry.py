"""Registries of techniques: one per family (bounds, densities, phases, lights, skies, shadings,
post effects, voxel materials, AOVs). Each entry is a `Kind`: its name, its schema model, its
function(s) and its capabilities, written once; the schema's choice tables, the planner and the
renderer all read them from here. "Adding a technique" in docs/ARCHITECTURE.md walks the path.
"""

from __future__ import annotations

import typing
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator

from pydantic import Discriminator, Field, Tag, create_model

from .models import One


@dataclass(frozen=True)
class Kind:
    """One technique: `name` (its key in the scene), `model` (the schema type of its table, or of
    its value), `fn` (the technique) and `caps` (capabilities the planner reads, e.g.
    ``homogeneous=True``); further functions of the same kind live in `caps` too."""

    name: str
    model: Any
    fn: Callable | None = None
    caps: dict[str, Any] = field(default_factory=dict)

    def __getattr__(self, name: str) -> Any:
        try:
            return self.caps[name]
        except KeyError:
            raise AttributeError(f"{self.name!r} has no capability {name!r}") from None


class Registry:
    """The kinds of one family, in registration order (the order they are offered in)."""

    def __init__(self, family: str):
        self.family = family
        self._kinds: dict[str, Kind] = {}

    def register(self, name: str, model: Any, fn: Callable | None = None, **caps: Any) -> Kind:
        """Adds the kind `name`: its schema `model`, its function `fn` and its capabilities `caps`;
        -> the `Kind`. A name registered twice is a ValueError."""
        if name in self._kinds:
            raise ValueError(f"{self.family}: {name!r} registered twice")
        kind = Kind(name, model, fn, caps)
        self._kinds[name] = kind
        return kind

    def __getitem__(self, name: str) -> Kind:
        return self._kinds[name]

    def __contains__(self, name: object) -> bool:
        return name in self._kinds

    def __iter__(self) -> Iterator[Kind]:
        return iter(self._kinds.values())

    def names(self) -> tuple[str, ...]:
        """The registered kinds' names, in the order they were registered."""
        return tuple(self._kinds)

    def one_of(self, model_name: str, doc: str, *, base: type[One] = One) -> type[One]:
        """The schema's one-key table: ``{ kind = {...} }`` with exactly one registered kind."""
        fields = {k.name: (k.model | None, Field(None)) for k in self}
        return create_model(model_name, __base__=base, __doc__=doc, __module__=base.__module__, **fields)

    def tagged_union(self, default: str) -> Any:
        """The schema type of a table chosen by its ``kind`` key (``default`` where it is absent)."""
        def tag(value: Any) -> str:
            return value.get("kind", default) if isinstance(value, dict) else getattr(value, "kind", default)

        members = tuple(typing.Annotated[k.model, Tag(k.name)] for k in self)
        return typing.Annotated[typing.Union[members], Discriminator(tag)]
