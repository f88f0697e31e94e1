"""Distributions: the one-key tables a recipe puts where a value goes, and their seeded draws.

A distribution is a one-key table whose key is a distribution name (these names are reserved in
recipes; no scene key uses them):

    sigma_t   = { uniform = [5, 20] }                       # also component-wise: [[0,0,0], [1,1,1]]
    frequency = { loguniform = [1, 8] }
    g         = { normal = { mean = 0.6, std = 0.1, min = 0.0, max = 0.9 } }   # clipped to [min, max]
    texture_seed = { integer = [0, 65535] }                 # inclusive
    phase     = { choice = ["isotropic", { hg = { g = 0.7 } }] }   # or { values = [...], weights = [...] }
    phase     = { choice = ["isotropic", { hg = { g = { uniform = [0.2, 0.8] } } }] }   # draws inside a choice
    direction = { hemisphere = { elevation = [10, 60], azimuth = [0, 360] } }   # unit vector, y up
    eye       = { orbit = { center = [0, 0, 0], distance = [3, 4], elevation = [5, 30], azimuth = [0, 360] } }

`orbit` places a point (a camera eye) at `distance` from `center` in the direction band.
A choice's values may hold distributions: they are drawn after the choice, only inside the value
chosen (each keyed by its path through the choice, `phase.choice[1].hg.g`).
Directions: azimuth is measured from +z towards +x, elevation above the y = 0 horizon, area-uniform
on the band of the sphere between the elevations (uniform in sin(elevation)). Each of `distance`,
`elevation`, `azimuth` is a number (fixed) or a [low, high] range.

Every draw comes from a `torch.Generator` seeded from a hash of (seed, index, key path): a sample
depends only on (seed, index), never on global RNG, other indices, or the other random keys.
"""

from __future__ import annotations

import copy
import hashlib
import math
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import torch

from ..scene.model import schema_keys
from ..schema.keypath import copy_plain, path_str, set_path
from ..schema.validate import (
    did_you_mean,
    fail,
    finite,
    integer,
    is_integer,
    known_keys,
)

DIST_KINDS = ("uniform", "loguniform", "normal", "integer", "choice", "hemisphere", "orbit")


def mix_seed(*parts: Any) -> int:
    """A 63-bit integer from a hash of `parts` (stable across processes, unlike hash())."""
    digest = hashlib.blake2b(repr(parts).encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") >> 1


def _uniform01(g: torch.Generator, n: int = 1) -> list[float]:
    return torch.rand(n, generator=g, dtype=torch.float64).tolist()


def _number(path: str, value: Any) -> float:
    return finite(path, value)


def _range(path: str, value: Any, *, what: str = "a [low, high] range") -> tuple[float, float]:
    """A number (fixed) or a [low, high] pair with low <= high."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        v = _number(path, value)
        return v, v
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        fail(path, value, f"expected a number or {what}")
    lo, hi = _number(f"{path}[0]", value[0]), _number(f"{path}[1]", value[1])
    if hi < lo:
        fail(path, value, "expected low <= high")
    return lo, hi


@dataclass(frozen=True)
class Dist:
    """One distribution at key path `path`; `spec` is its validated parameters."""

    path: str
    kind: str
    spec: Any

    def sample(self, g: torch.Generator) -> Any:
        """One value drawn from `g`: a number, a vector (list), an int or a choice's value."""
        k, s = self.kind, self.spec
        if k == "uniform":
            lo, hi, _ = s
            u = _uniform01(g, len(lo))
            out = [a + (b - a) * x for a, b, x in zip(lo, hi, u)]
            return out if s[2] else out[0]
        if k == "loguniform":
            lo, hi, _ = s
            u = _uniform01(g, len(lo))
            out = [math.exp(math.log(a) + (math.log(b) - math.log(a)) * x) for a, b, x in zip(lo, hi, u)]
            return out if s[2] else out[0]
        if k == "normal":
            mean, std, lo, hi = s
            x = mean + std * torch.randn(1, generator=g, dtype=torch.float64).item()
            return min(max(x, lo), hi)
        if k == "integer":
            lo, hi = s
            return int(torch.randint(lo, hi + 1, (1,), generator=g).item())
        if k == "choice":
            return copy_plain(s[0][self._pick(g)])
        if k == "hemisphere":
            return _direction(s, _uniform01(g, 2))
        if k == "orbit":
            target, distance, band = s
            u = _uniform01(g, 3)
            d = distance[0] + (distance[1] - distance[0]) * u[2]
            return [t + d * c for t, c in zip(target, _direction(band, u[:2]))]
        raise AssertionError(k)

    def _pick(self, g: torch.Generator) -> int:
        """A choice's value index, by its weights."""
        w = torch.tensor(self.spec[1], dtype=torch.float64)
        return int(torch.multinomial(w, 1, generator=g).item())

    def draw(self, seed: int, index: int, *salt: Any) -> Any:
        """The value of sample `index`: from a generator seeded by (seed, index, path, *salt); a choice
        then draws the distributions inside the value it picked (each from its own path's generator).
        `salt` tells apart several draws of one sample (a multi-view sample's cameras)."""
        g = torch.Generator().manual_seed(mix_seed("torchvol.recipe", int(seed), int(index), self.path, *salt))
        if self.kind != "choice" or not any(self.spec[2]):
            return self.sample(g)
        k = self._pick(g)
        value = copy_plain(self.spec[0][k])
        for rel, inner in self.spec[2][k].items():
            if not rel:
                return inner.draw(seed, index, *salt)  # the value is itself a distribution
            set_path(value, rel, inner.draw(seed, index, *salt))
        return value

    def corners(self) -> list[Any]:
        """Representative values (the extremes, every choice) used to validate a recipe up front."""
        k, s = self.kind, self.spec
        if k in ("uniform", "loguniform"):
            lo, hi = s[0], s[1]
            return [list(lo), list(hi)] if s[2] else [lo[0], hi[0]]
        if k == "normal":
            return [s[2] if math.isfinite(s[2]) else s[0] - 6 * s[1], s[3] if math.isfinite(s[3]) else s[0] + 6 * s[1]]
        if k == "integer":
            return [s[0], s[1]]
        if k == "choice":
            out = []
            for value, inners in zip(s[0], s[2]):
                corners = {rel: d.corners() for rel, d in inners.items()}
                for r in range(max((len(c) for c in corners.values()), default=1)):
                    v = copy.deepcopy(value)
                    for rel, c in corners.items():
                        if not rel:
                            v = c[r % len(c)]
                        else:
                            set_path(v, rel, c[r % len(c)])
                    out.append(v)
            return out
        if k == "hemisphere":
            return [_direction(s, [0.0, 0.0]), _direction(s, [1.0, 1.0])]
        target, distance, band = s
        return [[t + distance[i] * c for t, c in zip(target, _direction(band, [float(i)] * 2))] for i in (0, 1)]


def _direction(band: tuple, u: Sequence[float]) -> list[float]:
    """A unit vector in the elevation/azimuth band (degrees), area-uniform, from two uniforms."""
    (e0, e1), (a0, a1) = band
    s0, s1 = math.sin(math.radians(e0)), math.sin(math.radians(e1))
    y = s0 + (s1 - s0) * u[0]
    r = math.sqrt(max(0.0, 1.0 - y * y))
    az = math.radians(a0 + (a1 - a0) * u[1])
    return [r * math.sin(az), y, r * math.cos(az)]


def _band(path: str, spec: Any) -> tuple:
    allowed = ("elevation", "azimuth")
    if not isinstance(spec, Mapping):
        fail(path, spec, "expected a table { elevation = [lo, hi], azimuth = [lo, hi] }")
    for key in spec:
        if key not in allowed and key not in ("center", "distance"):
            fail(f"{path}.{key}", spec[key], "unknown key" + did_you_mean(key, allowed) + "; allowed: elevation, azimuth")
    elev = _range(f"{path}.elevation", spec.get("elevation", [0.0, 90.0]))
    if elev[0] < -90 or elev[1] > 90:
        fail(f"{path}.elevation", spec.get("elevation"), "elevations are degrees in [-90, 90]")
    return elev, _range(f"{path}.azimuth", spec.get("azimuth", [0.0, 360.0]))


def _components(path: str, value: Any) -> tuple[list[float], list[float], bool]:
    """uniform/loguniform bounds: [lo, hi] of numbers or of equal-length vectors."""
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        fail(path, value, "expected [low, high] (numbers, or two vectors of one length)")
    lo, hi = value
    vector = isinstance(lo, (list, tuple))
    if vector != isinstance(hi, (list, tuple)) or (vector and (len(lo) != len(hi) or not lo)):
        fail(path, value, "low and high must both be numbers or both vectors of one length")
    lo = [_number(f"{path}[0]", x) for x in (lo if vector else [lo])]
    hi = [_number(f"{path}[1]", x) for x in (hi if vector else [hi])]
    if any(b < a for a, b in zip(lo, hi)):
        fail(path, value, "expected low <= high (component-wise)")
    return lo, hi, vector


def parse_dist(path: str, table: Mapping) -> Dist:
    """Validate one distribution table (already known to have one key in DIST_KINDS)."""
    (kind, spec), = table.items()
    where = f"{path}.{kind}"
    if kind in ("uniform", "loguniform"):
        lo, hi, vector = _components(where, spec)
        if kind == "loguniform" and min(lo) <= 0:
            fail(where, spec, "loguniform bounds must be > 0")
        return Dist(path, kind, (lo, hi, vector))
    if kind == "normal":
        return Dist(path, kind, _normal(where, spec))
    if kind == "integer":
        if (not isinstance(spec, (list, tuple)) or len(spec) != 2
                or not all(is_integer(x) for x in spec) or spec[1] < spec[0]):
            fail(where, spec, "expected [low, high] integers, low <= high (inclusive)")
        return Dist(path, kind, (int(spec[0]), int(spec[1])))
    if kind == "choice":
        return Dist(path, kind, _choice(where, spec))
    if kind == "hemisphere":
        known_keys(where, spec if isinstance(spec, Mapping) else {}, ("elevation", "azimuth"))
        return Dist(path, kind, _band(where, spec))
    return Dist(path, kind, _orbit(where, spec))


def _normal(where: str, spec: Any) -> tuple[float, float, float, float]:
    """A normal distribution's (mean, std, min, max), validated (min/max infinite when not given)."""
    if not isinstance(spec, Mapping):
        fail(where, spec, "expected a table { mean = m, std = s, min = lo, max = hi } (min/max optional)")
    known_keys(where, spec, ("mean", "std", "min", "max"))
    if "mean" not in spec or "std" not in spec:
        fail(where, spec, "normal needs mean and std")
    mean, std = _number(f"{where}.mean", spec["mean"]), _number(f"{where}.std", spec["std"])
    if std < 0:
        fail(f"{where}.std", spec["std"], "expected std >= 0")
    lo = _number(f"{where}.min", spec["min"]) if "min" in spec else -math.inf
    hi = _number(f"{where}.max", spec["max"]) if "max" in spec else math.inf
    if hi < lo:
        fail(where, spec, "expected min <= max")
    return mean, std, lo, hi


def _choice(where: str, spec: Any) -> tuple[list, list[float], list[dict[str, Dist]]]:
    """A choice's (values, weights, the distributions inside each value by their path in it)."""
    values, weights = spec, None
    if isinstance(spec, Mapping):
        known_keys(where, spec, ("values", "weights"))
        values, weights = spec.get("values"), spec.get("weights")
    if not isinstance(values, (list, tuple)) or not values:
        fail(where, spec, "expected a non-empty list of values (or { values = [...], weights = [...] })")
    if weights is None:
        weights = [1.0] * len(values)
    if (not isinstance(weights, (list, tuple)) or len(weights) != len(values)
            or any(isinstance(w, bool) or not isinstance(w, (int, float)) or not math.isfinite(w) or w < 0 for w in weights)
            or sum(weights) <= 0):
        fail(f"{where}.weights", weights, f"expected {len(values)} finite weights >= 0, not all 0")
    inners = []
    for i, value in enumerate(values):
        found: dict[str, Dist] = {}
        find_dists(value, (f"{where}[{i}]",), found)  # full paths: errors and seeds name them
        inners.append({full[len(where) + len(f"[{i}]"):].lstrip("."): d for full, d in found.items()})
    return list(values), [float(w) for w in weights], inners


def _orbit(where: str, spec: Any) -> tuple[list[float], tuple[float, float], tuple]:
    """An orbit's (center [3], distance range, direction band), validated."""
    if not isinstance(spec, Mapping):
        fail(where, spec, "expected a table { center, distance, elevation, azimuth }")
    known_keys(where, spec, ("center", "distance", "elevation", "azimuth"))
    center = spec.get("center", [0.0, 0.0, 0.0])
    if not isinstance(center, (list, tuple)) or len(center) != 3:
        fail(f"{where}.center", center, "expected [x, y, z]")
    center = [_number(f"{where}.center[{i}]", x) for i, x in enumerate(center)]
    if "distance" not in spec:
        fail(where, spec, "orbit needs distance (a number or [low, high])")
    distance = _range(f"{where}.distance", spec["distance"])
    if distance[0] <= 0:
        fail(f"{where}.distance", spec["distance"], "expected distances > 0")
    return center, distance, _band(where, spec)


def _is_dist(node: Any) -> bool:
    return isinstance(node, Mapping) and len(node) == 1 and next(iter(node)) in DIST_KINDS


def find_dists(node: Any, loc: tuple, out: dict[str, Dist]) -> None:
    """Collect the distributions of a raw recipe dict, keyed by key path, in document order."""
    if _is_dist(node):
        path = path_str(loc)
        out[path] = parse_dist(path, node)
        return
    if isinstance(node, Mapping):
        for key, value in node.items():
            if isinstance(value, Mapping) and len(value) == 1 and next(iter(value)) not in DIST_KINDS:
                only = next(iter(value))
                hint = did_you_mean(str(only), DIST_KINDS)
                if hint and isinstance(only, str) and only not in schema_keys():
                    fail(path_str(loc + (key, only)), value[only], "unknown distribution" + hint + "; distributions: " + ", ".join(DIST_KINDS))
            find_dists(value, loc + (key,), out)
    elif isinstance(node, list):
        for i, value in enumerate(node):
            find_dists(value, loc + (i,), out)


def check_index(index: Any, seed: Any) -> None:
    """Refuse a sample index that is not an integer >= 0 or a seed that is not an integer."""
    integer("index", index, low=0)
    integer("seed", seed)
