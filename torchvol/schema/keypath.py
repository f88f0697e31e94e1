"""Key paths into nested scene data: ``volumes[0].sigma_t`` written, parsed, read and set."""

from __future__ import annotations

import copy
from typing import Any

import tomllib

from .validate import fail


def path_str(loc: tuple) -> str:
    """('volumes', 0, 'sigma_t') -> 'volumes[0].sigma_t'."""
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


def split(path: str) -> list[str]:
    """'a.b[0].c' (or 'a.b.0.c') -> ['a', 'b', '0', 'c']."""
    return [p for p in path.replace("[", ".").replace("]", "").split(".") if p]


def lookup(data: Any, loc: tuple | str, default: Any = None) -> Any:
    """The value at `loc` (a tuple of keys and indices, or a path string) in nested dicts and
    lists; `default` where there is none."""
    parts = loc if isinstance(loc, tuple) else tuple(int(p) if p.isdigit() else p for p in split(loc))
    for part in parts:
        try:
            data = data[part]
        except (KeyError, IndexError, TypeError):
            return default
    return data


def copy_plain(data: Any) -> Any:
    """A copy of nested scene data: dicts and lists copied, strings and numbers shared (immutable),
    anything else deep-copied. Twice as fast as `copy.deepcopy` on a TOML table (no memo, no
    dispatch): a recipe copies its template for every sample."""
    if isinstance(data, dict):
        return {k: copy_plain(v) for k, v in data.items()}
    if isinstance(data, list):
        return [copy_plain(v) for v in data]
    if data is None or isinstance(data, (str, int, float)):
        return data
    return copy.deepcopy(data)


def set_path(data: dict, dotted: str, value: Any) -> None:
    """Apply one override ``a.b[0].c`` / ``a.b.0.c`` to a nested dict/list, creating tables."""
    parts = split(dotted)
    if not parts:
        fail(dotted, value, "an override key must be a dotted path like 'camera.fov_y'")
    node: Any = data
    for i, part in enumerate(parts):
        last = i == len(parts) - 1
        if isinstance(node, list):
            if not part.isdigit() or int(part) >= len(node):
                where = path_str(tuple(int(p) if p.isdigit() else p for p in parts[: i + 1]))
                fail(where, value, f"index out of range (the list has {len(node)} items)")
            part = int(part)
        elif not isinstance(node, dict):
            fail(dotted, value, f"{'.'.join(parts[:i])} is not a table")
        if last:
            node[part] = value
        else:
            if isinstance(node, dict) and node.get(part) is None:  # absent, or an optional table left out (None)
                node[part] = {}
            node = node[part]


def parse_value(text: str) -> Any:
    """A command-line value: TOML syntax where it parses (numbers, [1,2,3], true), else a string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text
