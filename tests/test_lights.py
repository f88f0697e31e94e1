"""Point lights (torchvol/lights.py): single scattering in a homogeneous medium against a float64
quadrature along a ray that passes the light at distance h; the shadow ray ends at the light;
irradiance I·color/r² on voxel faces; refusals where a point light cannot serve."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import torchvol as tv
from torchvol.light.lights import POINT_RADIUS, Point, point_toward
from torchvol.light.phase import henyey_greenstein
from torchvol.schema.batch import stack

F64 = torch.float64
SIGMA, ALBEDO, G, INTENSITY = 1.5, 0.8, 0.4, 2.0
COLOR = np.array([1.0, 0.8, 0.6])


def ray_scene(h: float, light, *, shadow: bool, march: dict) -> dict:
    """A 1×1 image whose one ray runs along +z at height h through the box [−1, 1]³ (from z = −1 to
    z = 1), so it passes a light at the origin at distance h."""
    return {
        "image": {"width": 1, "height": 1, "spp": 1},
        "camera": {"eye": [0.0, h, -3.0], "target": [0.0, h, 0.0], "fov_y": 1.0},
        "lights": [{"kind": "point", "position": list(light), "color": COLOR.tolist(), "intensity": INTENSITY,
                    **({"shadow": {"steps": 1}} if shadow else {})}],
        "volumes": [{"bounds": {"box": {"min": [-1.0, -1.0, -1.0], "max": [1.0, 1.0, 1.0]}}, "density": {"constant": 1.0},
                     "sigma_t": SIGMA, "albedo": ALBEDO, "phase": {"hg": {"g": G}}}],
        "march": {"quality": "reference", "dither": "none", **march},
    }


def quadrature(h: float, light, *, shadow: bool, nodes: int = 400) -> np.ndarray:
    """L = ∫ e^{−σ(z+1)} σs p(θ) I·color/r² T_light dz over z in [−1, 1] (the ray's t − 2), in float64
    by Gauss–Legendre on pieces split where the integrand peaks (closest to the light)."""
    light = np.asarray(light, dtype=np.float64)
    x, w = np.polynomial.legendre.leggauss(nodes)
    edges = sorted({-1.0, 1.0, float(np.clip(light[2], -1.0, 1.0))})
    total = 0.0
    for a, b in zip(edges, edges[1:]):
        z = 0.5 * (b - a) * x + 0.5 * (a + b)
        p = np.stack([np.zeros_like(z), np.full_like(z, h), z], axis=1)
        v = light - p
        r = np.linalg.norm(v, axis=1)
        cos = v[:, 2] / r  # the ray runs along +z
        phase = henyey_greenstein(torch.from_numpy(cos), G).numpy()
        t_light = np.exp(-SIGMA * r * inside_fraction(p, v)) if shadow else 1.0
        f = np.exp(-SIGMA * (z + 1.0)) * SIGMA * ALBEDO * phase * INTENSITY / r**2 * t_light
        total += 0.5 * (b - a) * np.sum(w * f)
    return total * COLOR


def inside_fraction(p: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The part of each segment p → p + v inside the box [−1, 1]³ (p is inside)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(v != 0, (np.sign(v) - p) / v, np.inf).min(axis=1)
    return np.minimum(s, 1.0)


@pytest.mark.parametrize("h", [0.3, 0.8])
@pytest.mark.parametrize("light, shadow", [((0.0, 0.0, 0.0), True), ((0.0, 0.0, 0.0), False), ((0.2, 1.6, 0.3), True)],
                         ids=["inside, shadowed", "inside, unshadowed", "outside, shadowed"])
def test_single_scattering_matches_quadrature(h, light, shadow):
    want = quadrature(h, light, shadow=shadow)
    out = tv.render(ray_scene(h, light, shadow=shadow, march={"steps": 4096}))
    got = out.radiance[0, :, 0, 0].double().numpy()
    rel = np.abs(got - want).max() / want.max()
    assert rel < 2e-5, f"h = {h}, light {light}: got {got}, quadrature {want} (relative error {rel:.2e})"
    assert "volume0.march" in out.stats["passes"] and "volume0.closed_form" not in out.stats["passes"]
    assert ("volume0.shadow0" in out.stats["passes"]) == shadow


def test_error_controlled_march_meets_its_tolerance_near_the_light():
    """The tolerance is relative to the light's intensity·color: the 1/r² peak is found by step doubling."""
    want = quadrature(0.3, (0.0, 0.0, 0.0), shadow=True)
    out = tv.render(ray_scene(0.3, (0.0, 0.0, 0.0), shadow=True, march={"tolerance": 1e-4}))
    err = np.abs(out.radiance[0, :, 0, 0].double().numpy() - want).max() / (INTENSITY * COLOR.max())
    assert err < 1e-4, f"error {err:.2e} relative to the light"


def test_a_ray_through_the_light_stays_finite():
    """r² is capped at POINT_RADIUS²: a sample on the light sees I/POINT_RADIUS², never inf or NaN."""
    light = stack([tv.load_scene({"lights": [{"kind": "point", "position": [0.0, 0.0, 0.0]}]})]).lights[0]
    toward = point_toward(light, torch.zeros(1, 3), torch.zeros(1, dtype=torch.long))
    assert torch.isfinite(toward.irradiance).all() and toward.irradiance.max() == pytest.approx(1.0 / POINT_RADIUS**2, rel=1e-5)
    out = tv.render(ray_scene(0.0, (0.0, 0.0, 0.0), shadow=True, march={"steps": 64}), dtype=torch.float32)
    assert torch.isfinite(out.radiance).all()


def voxel_floor(light, *, blocker: tuple[int, int, int] | None = None) -> dict:
    """A 9×9 floor of voxels (top face at y = 1), seen from above, lit by one point light only."""
    grid = np.zeros((9, 3, 9), dtype=np.uint8)  # [k, j, i]
    grid[:, 0, :] = 1
    if blocker is not None:
        i, j, k = blocker
        grid[k, j, i] = 1
    return {
        "image": {"width": 24, "height": 24},
        "camera": {"eye": [4.5, 12.0, 4.5], "target": [4.5, 0.0, 4.5], "up": [0.0, 0.0, 1.0], "fov_y": 40.0},
        "lights": [{"kind": "point", "position": list(light), "color": [1.0, 0.5, 0.25], "intensity": 3.0,
                    "shadow": {"steps": 64}}],
        "voxels": {"occupancy": {"grid": {"data": grid}}, "ambient": [0.0, 0.0, 0.0], "face_tones": [1.0, 1.0, 1.0],
                   "materials": [[1.0, 1.0, 1.0]], "shadow": {"steps": 64, "offset": 1e-3}},
    }


def floor_points(out) -> tuple[torch.Tensor, torch.Tensor]:
    """World points [N, 3] of the pixels that see the floor's top face, and their pixels' radiance [N, 3]."""
    cam = out.camera
    v, u = torch.meshgrid(torch.arange(24.0), torch.arange(24.0), indexing="ij")
    depth = out.depth[0, 0]
    pix = torch.stack([u * depth, v * depth, depth], dim=-1).reshape(-1, 3)
    local = (torch.linalg.inv(cam.K[0]) @ pix.T).T
    c2w = torch.linalg.inv(cam.world_to_camera[0])
    world = local @ c2w[:3, :3].T + c2w[:3, 3]
    top = (depth.reshape(-1) > 0) & ((world[:, 1] - 1.0).abs() < 1e-3)
    return world[top], out.radiance[0].reshape(3, -1).T[top]


def test_voxel_faces_receive_intensity_over_r_squared():
    light = torch.tensor([4.0, 4.0, 5.0])
    out = tv.render(voxel_floor(light.tolist()))
    points, radiance = floor_points(out)
    v = light - points
    r2 = (v * v).sum(dim=1)
    want = 3.0 * torch.tensor([1.0, 0.5, 0.25]) * (v[:, 1] / r2.sqrt() / r2)[:, None]  # I·color·cos θ / r²
    assert points.shape[0] > 200
    err = (radiance - want).abs().max() / want.max()
    assert err < 1e-4, f"relative error {err:.2e}"


def test_the_shadow_ray_ends_at_the_light():
    """A voxel between the floor and the light shadows the floor; one beyond the light does not."""
    blocker = (4, 2, 4)  # the cell y in [2, 3) above the floor's centre (its top face at y = 1)
    between = tv.render(voxel_floor([4.5, 3.5, 4.5], blocker=blocker))
    assert (between.aovs["shadow"] == 0).sum().item() > 20, "the blocker below the light shadows the floor"
    beyond = tv.render(voxel_floor([4.5, 1.6, 4.5], blocker=blocker))  # the light sits between floor and blocker
    plain = tv.render(voxel_floor([4.5, 1.6, 4.5]))
    floor = (beyond.depth - 11.0).abs() < 1e-3  # the camera is 11 above the floor's top face
    assert floor.sum() > 200 and (plain.aovs["shadow"][floor] == 1).all()
    assert torch.equal(beyond.aovs["shadow"][floor], plain.aovs["shadow"][floor])
    assert torch.equal(beyond.radiance[floor.expand_as(beyond.radiance)], plain.radiance[floor.expand_as(plain.radiance)])


@pytest.mark.parametrize("scene, key", [
    ({"lights": [{"kind": "point", "shadow": {"method": "grid"}}], "volumes": [{}]}, "lights[0].shadow.method"),
    ({"lights": [{"kind": "point"}], "sky": {"kind": "atmosphere"}}, "sky.kind"),
    ({"lights": [{"kind": "point"}], "sky": {"halo": {"color": [1, 1, 1], "power": 2.0}}}, "sky.halo"),
    ({"lights": [{"kind": "point", "positon": [0, 1, 0]}]}, "lights[0].positon"),
    ({"lights": [{"kind": "point", "intensity": -1.0}]}, "lights[0].intensity"),
    ({"lights": [{"kind": "spot"}]}, "lights[0].kind"),
])
def test_refused_where_a_point_light_cannot_serve(scene, key):
    with pytest.raises(ValueError) as err:
        tv.load_scene(scene)
    assert str(err.value).startswith(key), str(err.value)


def test_point_schema_defaults():
    p = Point()
    assert p.kind == "point" and p.shadow is None and math.isclose(p.intensity, 1.0)
