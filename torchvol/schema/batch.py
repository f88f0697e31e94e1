"""A batch of scenes of one structure, seen as one: the roles of `torchvol.schema` applied.

`stack(models)` gives a `Stacked` view of B models of one class: a ``TENSOR`` field reads as a
(B, ...) tensor, an ``EACH`` field as a list of B values, a ``SHARED`` field as its one value, a
sub-model as a `Stacked` view of the B sub-models. `structure(model)` lists the leaves that must
agree for models to share a batch (``SHARED`` values, the presence of optional values, list
lengths and tensor shapes); `check_same_structure` refuses a batch where they do not, naming the
first key that differs. Both read the same role declarations, so the batch tensors and the
batch-structure check cannot drift apart: a value may differ between scenes exactly when the
renderer receives it per scene.
"""

from __future__ import annotations

import types
import typing
from functools import lru_cache
from typing import Any, Callable, Iterator, Sequence, Union

import numpy as np
import torch
from pydantic import BaseModel
from torch import Tensor

from ..ops.mathops import take_rows
from .keypath import path_str
from .models import EACH, SHARED, TENSOR, One, Role
from .validate import fail

# how a field batches, beyond the three declared roles: sub-models and lists of sub-models recurse
MODEL, MODELS = "model", "models"


def _strip(annotation: Any) -> tuple[Any, Role | None]:
    """The annotation without Optional/Annotated wrappers, and a role marker found on the way."""
    role = None
    while True:
        origin = typing.get_origin(annotation)
        if origin is typing.Annotated:
            marks = [m for m in annotation.__metadata__ if isinstance(m, Role)]
            role = role or (marks[0] if marks else None)
            annotation = annotation.__origin__
        elif origin in (Union, types.UnionType):
            args = [a for a in typing.get_args(annotation) if a is not type(None)]
            if len(args) != 1:
                return annotation, role  # a union of models (e.g. light kinds), or of plain types
            annotation = args[0]
        else:
            return annotation, role


def _is_model(annotation: Any) -> bool:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return True
    if typing.get_origin(annotation) in (Union, types.UnionType):
        return all(_is_model(_strip(a)[0]) for a in typing.get_args(annotation) if a is not type(None))
    return False


def _is_float_array(annotation: Any) -> bool:
    """float, or tuples/lists nested over float."""
    if annotation is float:
        return True
    if typing.get_origin(annotation) in (tuple, list):
        return all(a is Ellipsis or _is_float_array(_strip(a)[0]) for a in typing.get_args(annotation))
    return False


@lru_cache(maxsize=None)
def field_role(cls: type[BaseModel], name: str) -> Role | str:
    """TENSOR, EACH, SHARED, MODEL or MODELS for field `name` of model class `cls`."""
    info = cls.model_fields[name]
    marks = [m for m in info.metadata if isinstance(m, Role)]
    base, role = _strip(info.annotation)
    role = marks[0] if marks else role
    if role is not None:
        return role
    if _is_model(base):
        return MODEL
    if typing.get_origin(base) is list and _is_model(_strip(typing.get_args(base)[0])[0]):
        return MODELS
    return TENSOR if _is_float_array(base) else SHARED


class Stacked:
    """B models of one class seen as one (see the module docstring). `models` is the list itself,
    for code that treats each scene on its own (a loop over b); `len()` is B."""

    def __init__(self, models: Sequence[BaseModel], *, dtype: torch.dtype, device: torch.device):
        self.models = list(models)
        self._kw = dict(dtype=dtype, device=device)

    def __len__(self) -> int:
        return len(self.models)

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_") or name == "models":
            raise AttributeError(name)
        first = self.models[0]
        if name == "kind" and isinstance(first, One):
            value = first.kind  # structure: the same in every scene
        elif name == "value" and isinstance(first, One):
            value = self._view([m.value for m in self.models])
        elif name in type(first).model_fields:
            value = self._field(name)
        else:
            raise AttributeError(f"{type(first).__name__} has no field {name!r}")
        self.__dict__[name] = value  # computed once per batch
        return value

    def _view(self, values: list) -> Any:
        if values[0] is None:
            return None
        if isinstance(values[0], BaseModel):
            return Stacked(values, **self._kw)
        return self._tensor(values)  # a One choice that is a number, e.g. { constant = 1.0 }

    def _tensor(self, values: list) -> Tensor | None:
        if values[0] is None:
            return None
        dtype = torch.long if isinstance(np.asarray(values[0]).flat[0], (int, np.integer)) else self._kw["dtype"]
        return torch.tensor(values, dtype=dtype, device=self._kw["device"])

    def _field(self, name: str) -> Any:
        role = field_role(type(self.models[0]), name)
        values = [getattr(m, name) for m in self.models]
        if role is SHARED:
            return values[0]
        if role is EACH:
            return values
        if role is TENSOR:
            return self._tensor(values)
        if role == MODEL:
            return self._view(values)
        return [Stacked([v[i] for v in values], **self._kw) for i in range(len(values[0]))]


def stack(models: Sequence[BaseModel], *, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> Stacked:
    """The `models` (one a scene, of one type) as a `Stacked` batch: each numeric field a (B, ...)
    tensor of `dtype` on `device`."""
    return Stacked(models, dtype=dtype, device=torch.device(device))


def take(param: Tensor, s: Tensor) -> Tensor:
    """Per-scene `param` (B, ...) at scene indices `s` [n] -> [n, ...]. With one scene, a broadcast
    view: the gather would copy n rows of the same value (millions of samples per chunk)."""
    if param.shape[0] == 1:
        return param[0].expand(s.shape[0], *param.shape[1:])
    return take_rows(param, s)


def _shape(value: Any) -> Any:
    return None if value is None else np.shape(value)


def structure(model: BaseModel, loc: tuple = ()) -> Iterator[tuple[tuple, Any]]:
    """(key path, value) of every leaf that scenes of one batch must share, in schema order."""
    if isinstance(model, One):
        yield loc, model.kind
    for name in type(model).model_fields:
        value, role, here = getattr(model, name), field_role(type(model), name), loc + (name,)
        if role is SHARED and isinstance(value, BaseModel):  # a shared table: each of its keys, by name
            yield here, type(value).__name__
            yield from ((loc_, v) for loc_, v in _shared_leaves(value, here))
        elif role is SHARED:
            yield here, _hashable(value)
        elif role is TENSOR:
            yield here, _shape(value)
        elif role is EACH:
            yield here, value is None
        elif value is None:
            yield here, None
        elif role == MODEL:
            yield here, type(value).__name__
            yield from structure(value, here)
        else:
            yield here, len(value)
            for i, item in enumerate(value):
                yield here + (i,), type(item).__name__
                yield from structure(item, here + (i,))


def _shared_leaves(model: BaseModel, loc: tuple) -> Iterator[tuple[tuple, Any]]:
    for name in type(model).model_fields:
        value = getattr(model, name)
        if isinstance(value, BaseModel):
            yield loc + (name,), type(value).__name__
            yield from _shared_leaves(value, loc + (name,))
        else:
            yield loc + (name,), _hashable(value)


def _hashable(value: Any) -> Any:
    if isinstance(value, BaseModel):
        return tuple((k, _hashable(getattr(value, k))) for k in type(value).model_fields)
    if isinstance(value, (list, tuple)):
        return tuple(_hashable(v) for v in value)
    return value


def check_same_structure(scenes: Sequence[BaseModel]) -> None:
    """Scenes of one batch differ only in per-scene values: a SceneError naming the first key where
    scene b differs in structure from scene 0 (the dataset groups samples into batches by it)."""
    if len(scenes) < 2:  # (a scene's structure walk is ~0.7 ms: nothing to compare it with)
        return
    ref = list(structure(scenes[0]))
    for b, scene in enumerate(scenes[1:], start=1):
        for (loc, want), (loc_b, got) in zip(ref, structure(scene)):
            if loc != loc_b or want != got:
                where = path_str(loc_b if len(loc_b) <= len(loc) else loc)
                fail(f"scenes[{b}].{where}" if where else f"scenes[{b}]", got,
                     f"scenes rendered in one batch must share it (scenes[0] has {want!r}); "
                     "render them in separate batches")


def per_scene(points: Tensor, scene_index: Tensor, batch: int, fn: Callable[[int, Tensor | slice, Tensor], Tensor]) -> Tensor:
    """Evaluate `fn(b, index, points_b) -> [n_b]` on the points [N, ...] of each scene b, for state
    that cannot be gathered per point (a seed, a texture, a grid). `index` selects scene b's
    points from per-point tensors: an index tensor, or `slice(None)` when there is one scene."""
    if batch == 1:
        return fn(0, slice(None), points)
    out = None
    for b in range(batch):
        idx = (scene_index == b).nonzero().squeeze(1)
        if idx.numel():
            value = fn(b, idx, take_rows(points, idx))
            if out is None:
                out = value.new_zeros(points.shape[0], *value.shape[1:])
            out.index_copy_(0, idx, value)
    return points.new_zeros(points.shape[0]) if out is None else out


def structure_key(scene: BaseModel) -> tuple:
    """A hashable key: equal exactly for scenes that may share a batch."""
    return tuple(structure(scene))
