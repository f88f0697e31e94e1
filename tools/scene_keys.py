"""Write docs/SCENES.md: every scene key, its type, default and rule, read from the schema.

    python tools/scene_keys.py            # rewrite docs/SCENES.md
    python tools/scene_keys.py --check    # exit 1 if it is out of date (a test runs this)
"""

from __future__ import annotations

import re
import sys
import types
import typing
from pathlib import Path

from pydantic import BaseModel

from torchvol.scene import model as scene
from torchvol.schema.batch import MODEL, MODELS, field_role
from torchvol.schema.models import EACH, SHARED, TENSOR, nested_models

OUT = Path(__file__).resolve().parents[1] / "docs" / "SCENES.md"
BATCH = {TENSOR: "per scene", EACH: "per scene", SHARED: "shared", MODEL: "", MODELS: ""}


def _type_name(annotation) -> str:
    if typing.get_origin(annotation) is typing.Annotated:
        return _type_name(annotation.__origin__)
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation.__name__
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return " | ".join(_type_name(a) for a in typing.get_args(annotation))
    if typing.get_origin(annotation) is list:
        return f"list[{_type_name(typing.get_args(annotation)[0])}]"
    text = re.sub(r"\b[a-z_.]*\.([A-Z]\w*)", r"\1", str(annotation).replace("typing.", ""))
    return text.replace("<class '", "").replace("'>", "").replace("NoneType", "None")


def _kind(model: type[BaseModel]) -> str:
    """` (kind = "point")` for a table chosen by its kind key."""
    field = model.model_fields.get("kind")
    return f' (kind = "{field.default}")' if field is not None and typing.get_origin(field.annotation) is typing.Literal else ""


def _rules(field) -> str:
    symbols = {"ge": ">=", "gt": ">", "le": "<=", "lt": "<"}
    parts = [f"{symbols[k]} {getattr(m, k)}" for m in field.metadata for k in symbols if hasattr(m, k)]
    if field.description:
        parts.append(field.description)
    return "; ".join(parts)


def document(model: type[BaseModel], prefix: str, seen: set, lines: list[str], inherited: str | None = None) -> None:
    """`inherited`: the batch role of every key below a per-scene object or a shared table."""
    doc = (model.__doc__ or "").strip().splitlines()
    lines.append(f"\n## `{prefix or '(scene)'}`{_kind(model)} — {model.__name__}\n")
    if doc and not doc[0].startswith("!!!") and model.__doc__ != BaseModel.__doc__:
        lines.append(" ".join(d.strip() for d in doc) + "\n")
    lines.append("| key | type | default | batch | rule |\n| --- | --- | --- | --- | --- |")
    nested = []
    for name, field in model.model_fields.items():
        default = "required" if field.is_required() else (
            "(computed)" if field.default_factory is not None else repr(field.default))
        role = field_role(model, name)
        batch = inherited or BATCH[role]
        lines.append(f"| `{name}` | `{_type_name(field.annotation)}` | `{default}` | {batch} | {_rules(field)} |")
        listed = role == MODELS
        for sub in nested_models(field.annotation):
            if sub not in seen:
                seen.add(sub)
                below = inherited or (BATCH[role] if role in (EACH, SHARED) else None)
                nested.append((sub, (f"{prefix}.{name}" if prefix else name) + ("[]" if listed else ""), below))
    for sub, path, below in nested:
        document(sub, path, seen, lines, below)


def render_doc() -> str:
    lines = ["# Scene keys", "", "Generated from the schema (`torchvol/scene/model.py` and the technique modules it assembles) by",
             "`python tools/scene_keys.py`; do not edit.",
             "Tables with exactly one of several keys (bounds, density, phase) take one key only; lights and skies",
             "are chosen by their `kind` key. *batch*: a `per scene` value may differ between the scenes of one",
             "batch (`tv.render([a, b])`, a dataset's batches); a `shared` one must be equal in all of them (a",
             "batch that differs is refused, naming the key; datasets put such scenes in separate batches)."]
    document(scene.Scene, "", {scene.Scene}, lines)
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    text = render_doc()
    if "--check" in sys.argv:
        sys.exit(0 if OUT.exists() and OUT.read_text() == text else 1)
    OUT.write_text(text)
    print(f"wrote {OUT}")
