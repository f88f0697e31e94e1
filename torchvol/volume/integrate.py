"""Per-step integrators of the volume rendering equation, and a dense reference composite.

One march step covers a segment of length ``dt`` with extinction ``sigma_t`` and a source term
``source`` (radiance scattered or emitted towards the camera per unit length, divided by nothing).
Each integrator returns the segment's contribution *before* the transmittance in front of it and
the segment's own transmittance, so the march loop is the same for all of them:

    radiance += T * contribution;  T *= segment_transmittance

- ``riemann``:   contribution = S·dt                       (the seeds' naive S·dt)
- ``frostbite``: contribution = (S − S·e^{−σΔt}) / σ       (exact for S, σ constant on the segment)
- ``alpha``:     the seeds' premultiplied front-to-back compositing. Shader look: the medium gives
                 a = clamp(density·scale, 0, 1) directly; physical media: a = min(σΔt, 1) (the seeds'
                 `min(col.a * dt, 1)` mapping) with colour S/σ, so contribution = S·min(Δt, 1/σ)
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..ops import lanes


def one_minus_exp_over_x(x):
    """(1 − e^{−x}) / x for x ≥ 0, → 1 as x → 0 and → 1/x for huge x; lanes (`ops.lanes`), any
    shape. expm1 keeps it exact near 0 (relative error ~1e-7 in float32, ~1e-14 in float64 against
    the series), and x is clamped to the smallest normal number so that 0 gives 1, not 0/0: three
    ops, no branches."""
    safe = lanes.clamp_min(x, lanes.tiny(x))
    return -lanes.expm1(-safe) / safe


def frostbite_weight(sigma_t, dt):
    """(Δt·(1 − e^{−x})/x, e^{−x}) with x = σΔt, lanes: what a segment's source is multiplied by
    (`frostbite_step`) and its transmittance."""
    x = sigma_t * dt
    return dt * one_minus_exp_over_x(x), lanes.exp(-x)


def riemann_weight(sigma_t, dt):
    """(Δt, e^{−σΔt}), lanes: the naive step's source weight and its transmittance."""
    return dt, lanes.exp(-sigma_t * dt)


def alpha_linear_weight(sigma_t, dt):
    """(min(Δt, 1/σ), 1 − min(σΔt, 1)), lanes: `alpha_linear_step`'s source weight and transmittance."""
    return lanes.minimum(dt, 1.0 / sigma_t), 1.0 - lanes.clamp_max(sigma_t * dt, 1.0)


def riemann_step(source: Tensor, sigma_t: Tensor, dt: Tensor) -> tuple[Tensor, Tensor]:
    """Contribution S·Δt and transmittance. `source`: [N, C]; `sigma_t`, `dt`: [N]."""
    weight, trans = riemann_weight(sigma_t, dt)
    return source * weight[:, None], trans


def frostbite_step(source: Tensor, sigma_t: Tensor, dt: Tensor) -> tuple[Tensor, Tensor]:
    """Contribution (S − S e^{−σΔt})/σ, written as S·Δt·(1 − e^{−x})/x with x = σΔt (no 0/0).

    `source`: [N, C]; `sigma_t`, `dt`: [N]."""
    weight, trans = frostbite_weight(sigma_t, dt)
    return source * weight[:, None], trans


def alpha_step(color: Tensor, alpha: Tensor) -> tuple[Tensor, Tensor]:
    """The seeds' premultiplied compositing: contribution colour·a, transmittance 1 − a.

    `color`: [N, C]; `alpha`: [N] already in [0, 1]."""
    return color * alpha[:, None], 1.0 - alpha


def alpha_linear_step(source: Tensor, sigma_t: Tensor, dt: Tensor) -> tuple[Tensor, Tensor]:
    """The seeds' density→alpha mapping for a physical medium: a = min(σΔt, 1), colour S/σ.

    Contribution S·min(Δt, 1/σ) (1/0 = inf is fine in the min). `source`: [N, C];
    `sigma_t`, `dt`: [N]. First order; converges to the exact result as Δt → 0."""
    reach, trans = alpha_linear_weight(sigma_t, dt)
    return source * reach[:, None], trans


# each integrator's (source weight, transmittance) of a segment, lanes (the Dr.Jit march's step)
WEIGHTS = {"riemann": riemann_weight, "frostbite": frostbite_weight, "alpha": alpha_linear_weight}


def composite(contribution: Tensor, transmittance: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Dense front-to-back composite of S samples per ray: the obvious reference for the march loop.

    `contribution`: [R, S, C]; `transmittance`: [R, S] (per segment).
    Returns radiance [R, C], final transmittance [R], and weights w_i = T_i (1 − t_i) [R, S].
    """
    ones = torch.ones_like(transmittance[:, :1])
    before = torch.cumprod(torch.cat([ones, transmittance[:, :-1]], dim=1), dim=1)  # [R, S]
    radiance = (before[..., None] * contribution).sum(dim=1)
    weights = before * (1.0 - transmittance)
    return radiance, before[:, -1] * transmittance[:, -1], weights
