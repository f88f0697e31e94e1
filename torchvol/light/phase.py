"""Phase functions: the `PHASES` registry. Each kind is its schema model (the table under
`phase = { kind = ... }`, or its name alone: `phase = "isotropic"`) and its function
`fn(params (Stacked), cos_theta [n], scene_index [n]) -> p [n]`.

Physical phase functions are normalised over the sphere (∫ p dω = 1, HG includes 1/4π) and take
cos θ = dot(ray direction, sun direction) with the sun direction pointing towards the sun, so g > 0
is bright looking towards the sun. (The seeds' ``HenyeyGreenstein(dot(rd, -sundir))`` uses the
opposite sign with their sun directions and peaks looking away from the sun.)
"""

from __future__ import annotations

import math

import torch
from pydantic import Field, model_validator
from torch import Tensor

from ..ops import lanes
from ..schema.batch import take
from ..schema.models import One, Strict
from ..schema.registry import Registry

INV_4PI = 1.0 / (4.0 * math.pi)


def isotropic(cos_theta):
    """1/4π. `cos_theta`: [N] (lanes, `ops.lanes`)."""
    return lanes.full_like(cos_theta, INV_4PI)


def henyey_greenstein(cos_theta, g):
    """(1 − g²) / (4π (1 + g² − 2g cos θ)^{3/2}). `cos_theta`: [N]; `g`: [N] or scalar, |g| < 1
    (lanes, `ops.lanes`).

    The denominator is evaluated as `_hg_base`: no cancellation for g → ±1 at either peak."""
    g = _like(g, cos_theta)
    denom = _hg_base(cos_theta, g)
    return INV_4PI * (1.0 - g) * (1.0 + g) / (denom * lanes.sqrt(denom))


def _like(g, cos_theta):
    """A number `g` as a tensor of `cos_theta`'s type in torch (its float type, not Python's);
    lanes as they are."""
    if isinstance(cos_theta, Tensor):
        return torch.as_tensor(g, dtype=cos_theta.dtype, device=cos_theta.device)
    return g


def _hg_base(cos_theta, g):
    """1 + g² − 2g cos θ written (1 − |g|)² + 2|g|(1 − sign(g) cos θ): both terms ≥ 0, so the
    peak value (1 − |g|)² (cos θ = sign g) has no cancellation for either sign of g (lanes). cos θ
    is taken within [−1, 1]: a dot product of unit vectors can round past it, which at |g| near 1
    made the second term negative, the base 0 and the phase infinite."""
    a = lanes.abs(g)
    base = (1.0 - a) * (1.0 - a) + 2.0 * a * (1.0 - lanes.where(g < 0, -1.0, 1.0) * lanes.clamp(cos_theta, -1.0, 1.0))
    return lanes.clamp_min(base, lanes.tiny(cos_theta))


def dual_henyey_greenstein(cos_theta, g_forward, g_backward, weight):
    """mix(HG(g_forward), HG(g_backward), weight), the seeds' dual lobe. Arguments: [N] or scalar
    (lanes)."""
    return lanes.lerp(henyey_greenstein(cos_theta, g_forward), henyey_greenstein(cos_theta, g_backward),
                      _like(weight, cos_theta))


def rayleigh(cos_theta):
    """3/(16π) (1 + cos² θ). `cos_theta`: [N] (lanes)."""
    return (3.0 / (16.0 * math.pi)) * (1.0 + cos_theta * cos_theta)


def mie_cornette_shanks(cos_theta, g):
    """Cornette-Shanks Mie approximation 3(1−g²)(1+c²) / (8π(2+g²)(1+g²−2gc)^{3/2}), normalised
    (lanes)."""
    g = _like(g, cos_theta)
    denom = _hg_base(cos_theta, g)
    return (3.0 / (8.0 * math.pi)) * (1.0 - g) * (1.0 + g) * (1.0 + cos_theta * cos_theta) / (
        (2.0 + g * g) * denom * lanes.sqrt(denom))


class HG(Strict):
    g: float = Field(0.0, gt=-1.0, lt=1.0)


class DualHG(Strict):
    g_forward: float = Field(0.8, gt=-1.0, lt=1.0)
    g_backward: float = Field(-0.2, gt=-1.0, lt=1.0)
    weight: float = Field(0.5, ge=0.0, le=1.0)


class Empty(Strict):
    pass


class PhaseChoice(One):
    """A phase table, or a kind's name alone (``phase = "isotropic"``)."""

    @model_validator(mode="before")
    @classmethod
    def _shorthand(cls, data):
        return {data: {}} if isinstance(data, str) else data


# `anisotropic(params, cos, s, k [n])`: the kind with its anisotropy scaled by k (multiple
# scattering's octaves, `volume/multiple.py`): g·k for the HG lobes and Mie, a blend towards
# isotropic by k for the kinds without a g
# `lanes = (inputs(params, to), fn(q, cos, k))`: the kind in lanes (`ops.lanes`), what the Dr.Jit
# march traces for a light whose θ changes along a ray (a point light): `inputs` gathers its
# per-lane parameters (`to.per_lane`: per scene -> lanes), `fn` is `anisotropic` on them
PHASES = Registry("phase")
PHASES.register("isotropic", Empty, lambda p, cos, s: isotropic(cos), anisotropic=lambda p, cos, s, k: isotropic(cos),
                lanes=(lambda p, to: None, lambda q, cos, k: isotropic(cos)))
PHASES.register("hg", HG, lambda p, cos, s: henyey_greenstein(cos, take(p.g, s)),
                anisotropic=lambda p, cos, s, k: henyey_greenstein(cos, take(p.g, s) * k),
                lanes=(lambda p, to: to.per_lane(p.g), lambda g, cos, k: henyey_greenstein(cos, g * k)))
PHASES.register("dual_hg", DualHG, lambda p, cos, s: dual_henyey_greenstein(
    cos, take(p.g_forward, s), take(p.g_backward, s), take(p.weight, s)),
    anisotropic=lambda p, cos, s, k: dual_henyey_greenstein(cos, take(p.g_forward, s) * k, take(p.g_backward, s) * k,
                                                            take(p.weight, s)),
    lanes=(lambda p, to: (to.per_lane(p.g_forward), to.per_lane(p.g_backward), to.per_lane(p.weight)),
           lambda q, cos, k: dual_henyey_greenstein(cos, q[0] * k, q[1] * k, q[2])))
PHASES.register("rayleigh", Empty, lambda p, cos, s: rayleigh(cos),
                anisotropic=lambda p, cos, s, k: torch.lerp(isotropic(cos), rayleigh(cos), k),
                lanes=(lambda p, to: None, lambda q, cos, k: lanes.lerp(isotropic(cos), rayleigh(cos), k)))
PHASES.register("mie", HG, lambda p, cos, s: mie_cornette_shanks(cos, take(p.g, s)),
                anisotropic=lambda p, cos, s, k: mie_cornette_shanks(cos, take(p.g, s) * k),
                lanes=(lambda p, to: to.per_lane(p.g), lambda g, cos, k: mie_cornette_shanks(cos, g * k)))
