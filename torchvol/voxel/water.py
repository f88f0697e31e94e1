"""Water over a voxel world (seed 001 "Water Surface Rendering"): the plane y = `level` with
animated wave normals; a ray that reaches it splits into a reflected and a refracted ray (each
traced through the voxel DDA once, no further water), mixed by Fresnel; light travelling under
water is attenuated by Beer-Lambert, exp(−absorption · length).

The functions are plain tensor maths; `passes/water.py` runs them on the voxel surface's rays.
"""

from __future__ import annotations

from typing import Literal

import torch
from pydantic import Field, field_validator
from torch import Tensor

from ..schema.models import Strict, Vec3, nonneg

__all__ = ["VoxelWater", "WaterWaves", "beer", "fresnel", "plane_hit", "reflect", "refract", "wave_normal"]

Vec2 = tuple[float, float]


class WaterWaves(Strict):
    """The seed's two sine waves tilting the normal: n = normalize(a·sin(fx·x + sx·time), 1,
    a·cos(fz·z + sz·time)); frequency = (fx, fz), speed = (sx, sz). The defaults are the seed's."""

    amplitude: float = Field(0.05, ge=0.0)
    frequency: Vec2 = (3.0, 2.0)
    speed: Vec2 = (1.0, 0.7)


class VoxelWater(Strict):
    """A water plane at y = `level` (index of refraction `ior`, Beer-Lambert `absorption` per world
    unit, RGB); `fresnel`: "exact" (unpolarised dielectric) or "schlick" (the seed's form, F0 from
    ior). The plane is flat for intersection; only its normal moves with the waves."""

    level: float = 0.0
    ior: float = Field(1.33, gt=1.0, le=4.0)
    absorption: Vec3 = (0.4, 0.1, 0.05)
    waves: WaterWaves = Field(default_factory=WaterWaves)
    fresnel: Literal["exact", "schlick"] = "exact"
    offset: float = Field(0.01, ge=0.0)  # secondary rays start this far off the surface (the seed's 0.01)

    @field_validator("absorption")
    @classmethod
    def _absorption(cls, v):
        return nonneg(v)


def plane_hit(o: Tensor, d: Tensor, level: Tensor) -> Tensor:
    """Distance t [n] along rays o, d [n, 3] to the plane y = level [n]; inf where the ray runs
    parallel to it (d.y = 0, also when it lies in it), points away or starts on it (t ≤ 0)."""
    dy = d[:, 1]
    t = (level - o[:, 1]) / torch.where(dy == 0, torch.ones_like(dy), dy)
    return torch.where((dy != 0) & (t > 0), t, torch.full_like(t, torch.inf))


def wave_normal(x: Tensor, amplitude: Tensor, frequency: Tensor, speed: Tensor, time: Tensor) -> Tensor:
    """Unit upward normal [n, 3] of the water at points x [n, 3]; amplitude, time [n], frequency,
    speed [n, 2] (x and z waves)."""
    nx = amplitude * torch.sin(x[:, 0] * frequency[:, 0] + time * speed[:, 0])
    nz = amplitude * torch.cos(x[:, 2] * frequency[:, 1] + time * speed[:, 1])
    n = torch.stack([nx, torch.ones_like(nx), nz], dim=1)
    return n / torch.linalg.vector_norm(n, dim=1, keepdim=True)


def reflect(d: Tensor, n: Tensor) -> Tensor:
    """GLSL reflect: d − 2 (n·d) n; d, n [n, 3]."""
    return d - 2.0 * (d * n).sum(1, keepdim=True) * n


def refract(d: Tensor, n: Tensor, eta: Tensor) -> tuple[Tensor, Tensor]:
    """GLSL refract of unit d [n, 3] at the unit normal n [n, 3] facing the ray, eta = n1/n2 [n] ->
    (direction [n, 3] (0 under total internal reflection), tir [n] bool)."""
    cos_i = -(d * n).sum(1)
    k = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
    tir = k < 0
    cos_t = torch.sqrt(k.clamp_min(0.0))
    t = eta[:, None] * d + (eta * cos_i - cos_t)[:, None] * n
    return torch.where(tir[:, None], torch.zeros_like(t), t), tir


def fresnel(cos_i: Tensor, eta: Tensor, kind: str = "exact") -> Tensor:
    """Reflectance [n] of a dielectric interface at incidence cosine cos_i [n] (in [0, 1]), eta =
    n1/n2 [n] (≠ 1): unpolarised exact Fresnel, or Schlick with F0 = ((n1 − n2)/(n1 + n2))² and the
    cosine on the optically thinner side; 1 beyond the critical angle."""
    sin_t2 = eta * eta * (1.0 - cos_i * cos_i)
    tir = sin_t2 >= 1.0
    cos_t = torch.sqrt((1.0 - sin_t2).clamp_min(0.0))
    if kind == "schlick":
        f0 = ((eta - 1.0) / (eta + 1.0)) ** 2
        c = torch.where(eta > 1.0, cos_t, cos_i)
        m = (1.0 - c).clamp_min(0.0)
        f = f0 + (1.0 - f0) * (m * m) * (m * m) * m
    else:
        rs = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
        rp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
        f = 0.5 * (rs * rs + rp * rp)
    return torch.where(tir, torch.ones_like(f), f)


def beer(absorption: Tensor, length: Tensor) -> Tensor:
    """Beer-Lambert transmittance [n, 3] over length [n] (inf: a path that never ends, 0 or 1 by
    absorption) of absorption [n, 3]."""
    tau = absorption * length[:, None]
    return torch.exp(-torch.where(torch.isnan(tau), torch.zeros_like(tau), tau))  # 0·inf: clear water
