"""Multiple scattering by Wrenninge's octaves (Wrenninge, "Oz: the great and volumetric", 2013; as
in Frostbite's and Hillaire's cloud renderers): higher scattering orders are approximated by more
single-scattering "octaves" whose medium is made more transparent and whose phase less peaked.
Octave i scales σs by aⁱ, the extinction towards the light by bⁱ (T_light becomes T_light^(bⁱ)) and
the phase's anisotropy by cⁱ; the in-scatter is their sum over i < octaves. Octave 0 is single
scattering itself. Energy stays bounded (the sum ≤ 1/(1 − a) times octave 0's unshadowed value)
when a ≤ b, which the schema requires."""

from __future__ import annotations

import torch
from pydantic import Field, model_validator
from torch import Tensor

from ..ops.mathops import pow_
from ..schema.batch import take
from ..schema.models import Strict


class MultipleScattering(Strict):
    """`volumes[i].multiple_scattering`: Σ over octaves i of σs·aⁱ · p(θ; anisotropy·cⁱ) · E ·
    T_light^(bⁱ). a ≤ b (Wrenninge's condition for energy conservation)."""

    octaves: int = Field(4, ge=1, le=16)
    a: float = Field(0.5, ge=0.0, lt=1.0, description="scattering scale per octave")
    b: float = Field(0.5, gt=0.0, le=1.0, description="extinction scale towards the light per octave")
    c: float = Field(0.5, ge=0.0, le=1.0, description="phase anisotropy (g) scale per octave")

    @model_validator(mode="after")
    def _energy(self):
        if self.a > self.b:
            raise ValueError(f"a ({self.a}) must not exceed b ({self.b}): the octaves would add energy")
        return self


def octave_response(vol, irradiance: Tensor, cos: Tensor, s: Tensor) -> Tensor:
    """aⁱ · E · p(θ; cⁱ) [n, K, 3] of each octave i < K, for a light of irradiance `irradiance`
    [n, 3] at cos θ `cos` [n] of scenes `s` [n]."""
    ms, kind, params = vol.params.multiple_scattering, vol.phase, vol.params.phase.value
    a, c = take(ms.a, s), take(ms.c, s)
    out = [irradiance * kind.fn(params, cos, s)[:, None]]
    for i in range(1, ms.octaves):
        out.append(irradiance * (a**i * kind.caps["anisotropic"](params, cos, s, c**i))[:, None])
    return torch.stack(out, dim=1)


def octave_weights(sigma_s, transmittance, exponents) -> list:
    """σs · T^(bⁱ) of each octave i, lanes (`ops.lanes`): `sigma_s`, `transmittance` to the light
    (None: unshadowed), `exponents` bⁱ of the octaves i ≥ 1 (lanes or numbers) -> a lane per octave."""
    if transmittance is None:
        return [sigma_s] * (len(exponents) + 1)
    return [sigma_s * transmittance] + [sigma_s * pow_(transmittance, e) for e in exponents]


def octave_sum(vol, response: Tensor, sigma_s: Tensor, transmittance: Tensor | None, s: Tensor) -> Tensor:
    """Σᵢ σs · response_i · T^(bⁱ) [n, 3]: `response` [n, K, 3] from `octave_response`, `sigma_s`
    [n], `transmittance` [n] to the light (None: unshadowed) of scenes `s` [n]."""
    b = take(vol.params.multiple_scattering.b, s)
    weights = octave_weights(sigma_s, transmittance, [b**i for i in range(1, response.shape[1])])
    out = response[:, 0] * weights[0][:, None]
    for i in range(1, response.shape[1]):
        out = out + response[:, i] * weights[i][:, None]
    return out
