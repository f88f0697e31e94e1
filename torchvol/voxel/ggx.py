"""GGX PBR reflectance of voxel faces (seed 001, Variant 5): Cook-Torrance with the GGX
(Trowbridge-Reitz) distribution, Smith height-correlated visibility and Schlick Fresnel (F0 0.04
for dielectrics, the albedo for metals), plus the Lambert diffuse weighted (1 − F(n·v))(1 − metallic).

Plain functions on cosines [n] (or [n, 1] against colours [n, 3]), or on lanes (`ops.lanes`:
`reflectance_lanes`, the marched faces' `ggx_reflect` and the path tracer's one source). Safe in float32 and float64 at
the hard cases: roughness 0 clamps alpha = roughness² to `ALPHA_MIN` (a very sharp lobe, not a
delta), and grazing cosines are clamped to `COS_MIN` so nothing divides by zero.

Radiance uses the voxel surface's Lambert convention (a white Lambert face under irradiance E
reflects E · cos θ, i.e. π · BRDF · E · cos θ), so the diffuse part matches `materials.diffuse`."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..ops import lanes
from ..runtime.compilation import traced_vectors

ALPHA_MIN = 2e-3  # roughness 0: alpha² = 4e-6 keeps D finite in float32 (peak 1/(π α²) ≈ 8e4)
COS_MIN = 1e-4  # grazing: n·v, n·l floor (Filament's choice) keeps the visibility term finite
F0_DIELECTRIC = 0.04


def alpha_of(roughness: Tensor) -> Tensor:
    """Perceptual roughness [n] (or lanes) -> GGX alpha = roughness², floored at `ALPHA_MIN`."""
    return lanes.clamp_min(roughness * roughness, ALPHA_MIN)


def d_ggx(n_h: Tensor, alpha: Tensor, sin2: Tensor | None = None) -> Tensor:
    """GGX normal distribution D(h) = α² / (π ((n·h)² (α² − 1) + 1)²); n_h, alpha [n] (or lanes).
    With `sin2` = |n × h|² (`sin2_between`: 1 − (n·h)² for unit vectors) as α² / (π (|n × h|² +
    (n·h)² α²)²): near the lobe's peak 1 − (n·h)² cancels in float32 (D 19% off its float64 value
    at roughness 0, 11% at 0.05, at h a few 1e-4 from n); the cross product's is exact to a few
    ulps (8e-5 and 6e-5 there; Filament's form)."""
    a2 = alpha * alpha
    f = n_h * n_h * (a2 - 1.0) + 1.0 if sin2 is None else sin2 + n_h * n_h * a2
    return a2 / (math.pi * f * f)


def sin2_between(n: list, h: list, n_h_raw) -> object:
    """|n × h|² of a unit normal n and half vector h (three lanes each), `d_ggx`'s `sin2`; where
    n·h (`n_h_raw`, unclamped) ≤ 0 or h is no unit vector (v = −l: its length clamped, near 0)
    1 − (n·h)² of n·h clamped to [0, 1], as D takes it there."""
    x = [n[1] * h[2] - n[2] * h[1], n[2] * h[0] - n[0] * h[2], n[0] * h[1] - n[1] * h[0]]
    n_h = lanes.clamp(n_h_raw, 0.0, 1.0)
    return lanes.where((n_h_raw > 0.0) & (lanes.dot3(h, h) > 0.25), lanes.dot3(x, x), 1.0 - n_h * n_h)


def v_smith(n_v: Tensor, n_l: Tensor, alpha: Tensor) -> Tensor:
    """Smith height-correlated visibility V = G / (4 (n·l)(n·v)) =
    0.5 / (n·l √((n·v)²(1 − α²) + α²) + n·v √((n·l)²(1 − α²) + α²)); cosines clamped to COS_MIN."""
    a2 = alpha * alpha
    n_v, n_l = lanes.clamp_min(n_v, COS_MIN), lanes.clamp_min(n_l, COS_MIN)
    gv = n_l * lanes.sqrt(n_v * n_v * (1.0 - a2) + a2)
    gl = n_v * lanes.sqrt(n_l * n_l * (1.0 - a2) + a2)
    return 0.5 / (gv + gl)


def f_schlick(f0: Tensor, cos: Tensor) -> Tensor:
    """Schlick Fresnel F0 + (1 − F0)(1 − cos)⁵; f0 [n, 3] (or [n]), cos [n, 1] (or [n]) clamped to [0, 1]."""
    x = 1.0 - lanes.clamp(cos, 0.0, 1.0)
    x2 = x * x
    return f0 + (1.0 - f0) * (x2 * x2 * x)


def f0_of(albedo: Tensor, metallic: Tensor) -> Tensor:
    """Reflectance at normal incidence [n, 3]: 0.04 for dielectrics, the albedo [n, 3] for metals (metallic [n])."""
    m = metallic[:, None]
    return F0_DIELECTRIC * (1.0 - m) + albedo * m


def ggx_reflect(normal: Tensor, view: Tensor, light_dir: Tensor, albedo: Tensor, roughness: Tensor,
                metallic: Tensor, *, kernel: bool = False) -> Tensor:
    """π · BRDF · max(n·l, 0) [n, 3] (what unit irradiance from `light_dir` reflects towards `view`).

    normal, view (towards the eye), light_dir (towards the light) [n, 3] unit; albedo [n, 3];
    roughness, metallic [n]. Diffuse (1 − F(n·v))(1 − metallic) · albedo / π + specular D · V · F(v·h).
    `kernel`: `reflectance_lanes` as one Dr.Jit kernel (float32 on the CPU; its ~90 ops one pass
    over the hits, not ninety; its sqrt correctly rounded, torch's float32 one not)."""
    if kernel:
        return traced_vectors(lambda lane: reflectance_lanes(*(lanes.vector_lanes(x) for x in (normal, view, light_dir, albedo)),
                                                             lane(roughness), lane(metallic)), normal)
    col = lambda x: list(x.unbind(-1))  # noqa: E731
    return torch.stack(reflectance_lanes(col(normal), col(view), col(light_dir), col(albedo), roughness, metallic), dim=-1)


def reflectance_lanes(normal: list, view: list, light_dir: list, albedo: list, roughness, metallic) -> list:
    """`ggx_reflect` in lanes (three lanes each for the vectors and the albedo; roughness and
    metallic one): π · BRDF · max(n·l, 0), three lanes."""
    h = [view[c] + light_dir[c] for c in range(3)]
    norm = lanes.clamp_min(lanes.length3(*h), 1e-12)  # v = −l: any h, n·l ≤ 0 there
    h = [c / norm for c in h]
    n_l, n_v = lanes.dot3(normal, light_dir), lanes.dot3(normal, view)
    n_h_raw, v_h = lanes.dot3(normal, h), lanes.dot3(view, h)
    n_h = lanes.clamp(n_h_raw, 0.0, 1.0)
    alpha = alpha_of(roughness)
    lobe = d_ggx(n_h, alpha, sin2_between(normal, h, n_h_raw)) * v_smith(n_v, n_l, alpha)
    cos = math.pi * lanes.clamp_min(n_l, 0.0)
    out = []
    for c in range(3):
        f0 = F0_DIELECTRIC * (1.0 - metallic) + albedo[c] * metallic  # `f0_of`
        # the diffuse keeps what the specular lobe as a whole does not reflect towards v: 1 − F(n·v)
        # (the seed's Fresnel weight); 1 − F(v·h) per light would exceed 1 at grazing views
        diffuse = (1.0 - f_schlick(f0, n_v)) * (1.0 - metallic) * albedo[c] / math.pi
        out.append(cos * (diffuse + lobe * f_schlick(f0, v_h)))
    return out


__all__ = ["ALPHA_MIN", "COS_MIN", "alpha_of", "d_ggx", "f0_of", "f_schlick", "ggx_reflect", "reflectance_lanes", "sin2_between", "v_smith"]
