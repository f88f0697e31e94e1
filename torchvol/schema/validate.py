"""The one boundary check: every user-input error is raised here, naming key path, value and rule."""

from __future__ import annotations

import difflib
import math
from typing import Any, Iterable, Mapping, NoReturn, Sequence

import numpy as np


class SceneError(ValueError):
    """Bad user input: `path` is the key path (e.g. ``volumes[0].sigma_t``)."""

    def __init__(self, path: str, value: Any, allowed: str):
        self.path, self.value, self.allowed = path, value, allowed
        super().__init__(f"{path or '<root>'}: got {value!r}; {allowed}")


def fail(path: str, value: Any, allowed: str) -> NoReturn:
    """Refuses user input: raises SceneError naming the key `path`, the `value` given and what is
    `allowed`."""
    raise SceneError(path, value, allowed)


def did_you_mean(word: str, choices: Iterable[str]) -> str:
    """The hint " (did you mean 'x'?)" for the closest of `choices` to `word`, or "" where none is
    close."""
    close = difflib.get_close_matches(word, list(choices), n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


def known_keys(path: str, table: Mapping, allowed: Sequence[str]) -> None:
    """Refuses a key of `table` (at `path`) that is not in `allowed`, naming it, a near match and
    what is allowed."""
    for key in table:
        if key not in allowed:
            fail(f"{path}.{key}", table[key], "unknown key" + did_you_mean(key, allowed) + "; allowed: " + ", ".join(allowed))


def finite(path: str, value: Any, *, low: float | None = None, above: float | None = None, why: str = "") -> float:
    """The one check of a real number: finite (bools refused), at least `low` / more than `above`
    where given; `why` is said in the message."""
    ok = not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(value)
    if not ok or (low is not None and value < low) or (above is not None and not value > above):
        rule = f" >= {low}" if low is not None else f" > {above}" if above is not None else ""
        fail(path, value, f"expected a finite number{rule}" + (f" ({why})" if why else ""))
    return float(value)


def is_integer(value: Any) -> bool:
    """An int (or numpy integer) that is not a bool: Python counts True as the int 1."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def integer(path: str, value: Any, *, low: int | None = None) -> int:
    """The one check of integer input: an integer, bools refused, at least `low` where given."""
    if not is_integer(value) or (low is not None and value < low):
        fail(path, value, "expected an integer" + (f" >= {low}" if low is not None else ""))
    return int(value)
