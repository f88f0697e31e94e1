"""The building blocks of the scene schema: strict models, one-of tables, and how each value
batches.

Every model forbids unknown keys and non-finite numbers. Every field has a batch role, declared
once, here in the schema, and read by `torchvol.schema.batch` both to build a batch's tensors and to
decide which scenes may share a batch:

- ``TENSOR`` (per-scene number): scenes of one batch may differ; the renderer sees a (B, ...)
  tensor. The default for floats and tuples or lists of floats.
- ``EACH`` (per-scene object): scenes may differ; the renderer sees a list of B values and treats
  each scene on its own (a seed, an array, a texture, an occupancy built per scene).
- ``SHARED`` (structure): every scene of a batch must hold the same value; the renderer sees it
  once. The default for everything else (ints such as step counts, strings, modes, flags).

Mark a field otherwise with ``Annotated[type, EACH]`` (or ``SHARED``, ``TENSOR``).
"""

from __future__ import annotations

import math
import typing
from collections.abc import Mapping
from enum import Enum
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, model_validator
from pydantic_core import PydanticCustomError

from .validate import did_you_mean

Vec3 = tuple[float, float, float]


class Role(Enum):
    TENSOR = "tensor"
    EACH = "each"
    SHARED = "shared"


TENSOR, EACH, SHARED = Role.TENSOR, Role.EACH, Role.SHARED


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, arbitrary_types_allowed=True, frozen=True)

    @model_validator(mode="before")
    @classmethod
    def _known_keys(cls, data: Any) -> Any:
        if isinstance(data, Mapping):
            for key in data:
                if key not in cls.model_fields:
                    allowed = ", ".join(cls.model_fields)
                    raise PydanticCustomError(
                        "unknown_key",
                        "unknown key{hint}; allowed keys: {allowed}",
                        {"key": str(key), "hint": did_you_mean(str(key), cls.model_fields), "allowed": allowed},
                    )
        return data


class One(Strict):
    """A choice written as a table with exactly one key, e.g. ``{ box = {...} }``; the key (`kind`)
    is structure, shared by a batch."""

    @model_validator(mode="after")
    def _exactly_one(self):
        given = [k for k in type(self).model_fields if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError(f"give exactly one of {', '.join(type(self).model_fields)}")
        return self

    @property
    def kind(self) -> str:
        """The name of the one key that is set."""
        return next(k for k in type(self).model_fields if getattr(self, k) is not None)

    @property
    def value(self) -> Any:
        """The value of the one key that is set (its model)."""
        return getattr(self, self.kind)


def refuse(path: str, value: Any, allowed: str):
    """A cross-key rule broken: an error naming `path` (from the scene's root), not the model's."""
    raise PydanticCustomError("at_path", "{allowed}", {"path": path, "value": value, "allowed": allowed})


def nonneg(v: Vec3, what: str = "components") -> Vec3:
    """`v` unchanged; a ValueError where a component is negative (`what`: the components' name in
    the message)."""
    if min(v) < 0:
        raise ValueError(f"{what} must be >= 0")
    return v


def nonzero(v: Vec3, why: str) -> Vec3:
    """A direction: refused where its length is 0 (it could not be normalised)."""
    if math.hypot(*v) < 1e-12:
        raise ValueError(f"direction must be a non-zero vector ({why})")
    return v


class GridSource(Strict):
    """A 3D array given as `path` (a .npy file) or `data` (an array or tensor), indexed [k, j, i];
    per scene (a batch may hold a different array for each scene)."""

    path: Annotated[str | None, EACH] = None
    data: Annotated[Any, EACH] = None

    def _check(self, array: np.ndarray) -> np.ndarray:
        """Subclasses: validate the values and return the stored array."""
        raise NotImplementedError

    @model_validator(mode="after")
    def _load(self):
        if (self.path is None) == (self.data is None):
            raise ValueError("give path (a .npy file) or data (an array), not both")
        if self.path is not None:
            if not Path(self.path).is_file():
                raise ValueError(f"no such file: {self.path}")
            array = np.load(self.path)
        else:
            array = np.asarray(self.data.numpy() if hasattr(self.data, "numpy") else self.data)
        if array.ndim != 3 or min(array.shape) < 1:
            raise ValueError(f"grid must be a 3D array [k, j, i], got shape {array.shape}")
        object.__setattr__(self, "data", self._check(array))
        return self


def nested_models(annotation: Any) -> list[type[BaseModel]]:
    """The model classes inside a field annotation (through Optional, unions, lists, Annotated)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for arg in typing.get_args(annotation) for m in nested_models(arg)]


def reachable_models(root: type[BaseModel]) -> list[type[BaseModel]]:
    """Every model class reachable from `root` through its fields, `root` first."""
    seen: list[type[BaseModel]] = []
    todo = [root]
    while todo:
        cls = todo.pop(0)
        if cls in seen:
            continue
        seen.append(cls)
        todo += [m for f in cls.model_fields.values() for m in nested_models(f.annotation)]
    return seen
