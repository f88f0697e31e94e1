"""GGX PBR reflectance of voxel faces (seed 001, Variant 5): Cook-Torrance with the GGX
(Trowbridge-Reitz) distribution, Smith height-correlated visibility and Schlick Fresnel (F0 0.04
for dielectrics, the albedo for metals), plus the Lambert diffuse weighted (1 − F(n·v))(1 − metallic).

Plain functions on cosines [n] (or [n, 1] against colours [n, 3]). Safe in float32 and float64 at
the hard cases: roughness 0 clamps alpha = roughness² to `ALPHA_MIN` (a very sharp lobe, not a
delta), and grazing cosines are clamped to `COS_MIN` so nothing divides by zero.

Radiance uses the voxel surface's Lambert convention (a white Lambert face under irradiance E
reflects E · cos θ, i.e. π · BRDF · E · cos θ), so the diffuse part matches `materials.diffuse`."""

from __future__ import annotations

import math

import torch
from torch import Tensor

ALPHA_MIN = 2e-3  # roughness 0: alpha² = 4e-6 keeps D finite in float32 (peak 1/(π α²) ≈ 8e4)
COS_MIN = 1e-4  # grazing: n·v, n·l floor (Filament's choice) keeps the visibility term finite
F0_DIELECTRIC = 0.04


def alpha_of(roughness: Tensor) -> Tensor:
    """Perceptual roughness [n] -> GGX alpha = roughness², floored at `ALPHA_MIN`."""
    return (roughness * roughness).clamp_min(ALPHA_MIN)


def d_ggx(n_h: Tensor, alpha: Tensor) -> Tensor:
    """GGX normal distribution D(h) = α² / (π ((n·h)² (α² − 1) + 1)²); n_h, alpha [n]."""
    a2 = alpha * alpha
    f = n_h * n_h * (a2 - 1.0) + 1.0
    return a2 / (math.pi * f * f)


def v_smith(n_v: Tensor, n_l: Tensor, alpha: Tensor) -> Tensor:
    """Smith height-correlated visibility V = G / (4 (n·l)(n·v)) =
    0.5 / (n·l √((n·v)²(1 − α²) + α²) + n·v √((n·l)²(1 − α²) + α²)); cosines clamped to COS_MIN."""
    a2 = alpha * alpha
    n_v, n_l = n_v.clamp_min(COS_MIN), n_l.clamp_min(COS_MIN)
    gv = n_l * torch.sqrt(n_v * n_v * (1.0 - a2) + a2)
    gl = n_v * torch.sqrt(n_l * n_l * (1.0 - a2) + a2)
    return 0.5 / (gv + gl)


def f_schlick(f0: Tensor, cos: Tensor) -> Tensor:
    """Schlick Fresnel F0 + (1 − F0)(1 − cos)⁵; f0 [n, 3] (or [n]), cos [n, 1] (or [n]) clamped to [0, 1]."""
    x = 1.0 - cos.clamp(0.0, 1.0)
    x2 = x * x
    return f0 + (1.0 - f0) * (x2 * x2 * x)


def f0_of(albedo: Tensor, metallic: Tensor) -> Tensor:
    """Reflectance at normal incidence [n, 3]: 0.04 for dielectrics, the albedo [n, 3] for metals (metallic [n])."""
    m = metallic[:, None]
    return F0_DIELECTRIC * (1.0 - m) + albedo * m


def ggx_reflect(normal: Tensor, view: Tensor, light_dir: Tensor, albedo: Tensor, roughness: Tensor,
                metallic: Tensor) -> Tensor:
    """π · BRDF · max(n·l, 0) [n, 3] (what unit irradiance from `light_dir` reflects towards `view`).

    normal, view (towards the eye), light_dir (towards the light) [n, 3] unit; albedo [n, 3];
    roughness, metallic [n]. Diffuse (1 − F(n·v))(1 − metallic) · albedo / π + specular D · V · F(v·h)."""
    h = view + light_dir
    h = h / torch.linalg.vector_norm(h, dim=-1, keepdim=True).clamp_min(1e-12)  # v = −l: any h, n·l ≤ 0 there
    n_l = (normal * light_dir).sum(-1)
    n_v = (normal * view).sum(-1)
    n_h = (normal * h).sum(-1).clamp(0.0, 1.0)
    v_h = (view * h).sum(-1)
    alpha, f0 = alpha_of(roughness), f0_of(albedo, metallic)
    spec = (d_ggx(n_h, alpha) * v_smith(n_v, n_l, alpha))[:, None] * f_schlick(f0, v_h[:, None])
    # the diffuse keeps what the specular lobe as a whole does not reflect towards v: 1 − F(n·v)
    # (the seed's Fresnel weight); 1 − F(v·h) per light would exceed 1 at grazing views
    diffuse = (1.0 - f_schlick(f0, n_v[:, None])) * (1.0 - metallic)[:, None] * albedo / math.pi
    return (math.pi * n_l.clamp_min(0.0))[:, None] * (diffuse + spec)


__all__ = ["ALPHA_MIN", "COS_MIN", "alpha_of", "d_ggx", "f0_of", "f_schlick", "ggx_reflect", "v_smith"]
