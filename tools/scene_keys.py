"""Write docs/SCENES.md: every scene key, its type, default and rule, read from the schema.

    python tools/scene_keys.py            # rewrite docs/SCENES.md
    python tools/scene_keys.py --check    # exit 1 if it is out of date (a test runs this)
"""

from __future__ import annotations

import sys
import typing
from pathlib import Path

from pydantic import BaseModel

from torchvol import scene

OUT = Path(__file__).resolve().parents[1] / "docs" / "SCENES.md"


def _models(annotation) -> list[type[BaseModel]]:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for arg in typing.get_args(annotation) for m in _models(arg)]


def _type_name(annotation) -> str:
    text = str(annotation).replace("typing.", "").replace("torchvol.scene.", "")
    return text.replace("<class '", "").replace("'>", "").replace("NoneType", "None")


def _rules(field) -> str:
    symbols = {"ge": ">=", "gt": ">", "le": "<=", "lt": "<"}
    parts = [f"{symbols[k]} {getattr(m, k)}" for m in field.metadata for k in symbols if hasattr(m, k)]
    if field.description:
        parts.append(field.description)
    return "; ".join(parts)


def document(model: type[BaseModel], prefix: str, seen: set, lines: list[str]) -> None:
    doc = (model.__doc__ or "").strip().splitlines()
    lines.append(f"\n## `{prefix or '(scene)'}` — {model.__name__}\n")
    if doc and not doc[0].startswith("!!!") and model.__doc__ != BaseModel.__doc__:
        lines.append(" ".join(d.strip() for d in doc) + "\n")
    lines.append("| key | type | default | rule |\n| --- | --- | --- | --- |")
    nested = []
    for name, field in model.model_fields.items():
        default = "required" if field.is_required() else (
            "(computed)" if field.default_factory is not None else repr(field.default))
        lines.append(f"| `{name}` | `{_type_name(field.annotation)}` | `{default}` | {_rules(field)} |")
        for sub in _models(field.annotation):
            if sub not in seen:
                seen.add(sub)
                nested.append((sub, f"{prefix}.{name}" if prefix else name))
    for sub, path in nested:
        document(sub, path, seen, lines)


def render_doc() -> str:
    lines = ["# Scene keys", "", "Generated from `torchvol/scene.py` by `python tools/scene_keys.py`; do not edit.",
             "Tables with exactly one of several keys (bounds, density, phase) take one key only."]
    document(scene.Scene, "", {scene.Scene}, lines)
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    text = render_doc()
    if "--check" in sys.argv:
        sys.exit(0 if OUT.exists() and OUT.read_text() == text else 1)
    OUT.write_text(text)
    print(f"wrote {OUT}")
