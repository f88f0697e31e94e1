"""Depth + exported camera -> world points on the rendered surfaces (DESIGN: `depth_to_3d(depth, K)`
followed by the inverse of `world_to_camera` gives world points on the surfaces).

A dense homogeneous medium (σ = 1e4) acts as a surface: its expected termination depth lies within
~1/σ of the entry point. Unprojected with kornia's `depth_to_3d_v2` / `depth_to_3d`, the points
must land on the bounds' surface, for odd and non-square image sizes and for B = 2 scenes rendered
in one call.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import assert_close
from kornia.geometry.depth import depth_to_3d, depth_to_3d_v2

import torchvol as tv

SIGMA = 1e4


def _scene(eye, target, bounds, width, height, fov=30.0):
    return {
        "image": {"width": width, "height": height},
        "camera": {"eye": eye, "target": target, "fov_y": fov},
        "volumes": [{"bounds": bounds, "density": {"constant": 1.0}, "sigma_t": SIGMA, "albedo": 0.0}],
    }


def _world_points(out, use_v2: bool = True) -> torch.Tensor:
    """(B, H, W, 3) world points from depth, K and world_to_camera, via kornia."""
    depth = out.depth.double()
    K = out.camera.K.double()
    if use_v2:
        cam_pts = depth_to_3d_v2(depth[:, 0], K)  # (B, H, W, 3)
    else:
        cam_pts = depth_to_3d(depth, K).permute(0, 2, 3, 1)  # (B, 3, H, W) -> (B, H, W, 3)
    c2w = torch.linalg.inv(out.camera.world_to_camera.double())  # (B, 4, 4)
    return torch.einsum("bij,bhwj->bhwi", c2w[:, :3, :3], cam_pts) + c2w[:, None, None, :3, 3]


def _sphere_sdf(p, center, radius):
    return torch.linalg.vector_norm(p - torch.as_tensor(center, dtype=p.dtype), dim=-1) - radius


def _box_sdf(p, lo, hi):
    lo, hi = torch.as_tensor(lo, dtype=p.dtype), torch.as_tensor(hi, dtype=p.dtype)
    c, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
    q = (p - c).abs() - h
    outside = torch.linalg.vector_norm(q.clamp_min(0), dim=-1)
    inside = q.amax(dim=-1).clamp_max(0)
    return outside + inside


SIZES = [(9, 7), (16, 11), (5, 13), (21, 21)]


@pytest.mark.parametrize("width,height", SIZES)
@pytest.mark.parametrize("use_v2", [True, False])
def test_sphere_depth_unprojects_onto_surface_batched(width, height, use_v2):
    centers = [[0.2, -0.1, 0.3], [-0.4, 0.5, 1.0]]
    radii = [1.0, 0.6]
    eyes = [[1.0, 1.5, -3.0], [-2.5, 0.2, 3.5]]
    scenes = [_scene(e, c, {"sphere": {"center": c, "radius": r}}, width, height) for e, c, r in zip(eyes, centers, radii)]
    out = tv.render(scenes)
    assert out.depth.shape == (2, 1, height, width)
    pts = _world_points(out, use_v2)
    for b in range(2):
        hit = out.depth[b, 0] > 0
        assert hit.float().mean() > 0.1, f"scene {b}: the sphere should cover the middle of the picture"
        # the centre of the picture looks at the sphere's centre
        assert out.depth[b, 0, height // 2, width // 2] > 0
        scale = float(np.linalg.norm(np.subtract(eyes[b], centers[b])))
        sdf = _sphere_sdf(pts[b][hit], centers[b], radii[b])
        # inside the medium by about 1/σ (planar depth is the expected termination depth)
        assert_close(sdf, torch.zeros_like(sdf), atol=1e-3 * scale, what=f"sphere {width}x{height} scene {b} sdf")
        assert (sdf < 2e-4 * scale).all()
        # no hit where the sphere is not: depth 0 outside the silhouette
        assert (out.depth[b, 0][~hit] == 0).all()
        assert (out.alpha[b, 0][~hit] < 0.01 + 1e-6).all()


@pytest.mark.parametrize("width,height", SIZES[:3])
def test_box_depth_unprojects_onto_surface_batched(width, height):
    boxes = [([-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]), ([-1.0, -0.2, 0.0], [0.3, 0.9, 2.0])]
    eyes = [[1.3, 1.1, -2.2], [2.0, -1.5, 4.0]]
    targets = [[0.0, 0.0, 0.0], [-0.35, 0.35, 1.0]]
    scenes = [_scene(e, t, {"box": {"min": lo, "max": hi}}, width, height) for e, t, (lo, hi) in zip(eyes, targets, boxes)]
    out = tv.render(scenes)
    pts = _world_points(out)
    for b in range(2):
        hit = out.depth[b, 0] > 0
        assert hit.float().mean() > 0.1
        scale = float(np.linalg.norm(np.subtract(eyes[b], targets[b])))
        sdf = _box_sdf(pts[b][hit], *boxes[b])
        assert_close(sdf, torch.zeros_like(sdf), atol=1e-3 * scale, what=f"box {width}x{height} scene {b} sdf")


def test_depth_matches_camera_projection():
    """The exported camera projects each unprojected point back to its own pixel centre."""
    scenes = [_scene([0.5, 2.0, -3.0], [0.0, 0.0, 0.0], {"sphere": {"center": [0, 0, 0], "radius": 1.2}}, 11, 8, fov=35.0)]
    out = tv.render(scenes)
    pts = _world_points(out)[0]
    hit = out.depth[0, 0] > 0
    proj = out.camera.project(pts[hit].to(out.camera.K.dtype))
    rows, cols = hit.nonzero(as_tuple=True)
    assert_close(proj[:, 0].double(), cols.double(), atol=1e-3, what="projected column")
    assert_close(proj[:, 1].double(), rows.double(), atol=1e-3, what="projected row")
    assert_close(proj[:, 2].double(), out.depth[0, 0][hit].double(), atol=1e-5, what="projected camera z")


def test_principal_point_and_focal_exported():
    """K follows DESIGN: fy = H / (2 tan(fov_y/2)), cx = W/2 − 0.5, cy = H/2 − 0.5."""
    out = tv.render(_scene([0.0, 0.0, -3.0], [0.0, 0.0, 0.0], {"sphere": {"center": [0, 0, 0], "radius": 1.0}}, 13, 6, fov=40.0))
    K = out.camera.K[0].double()
    fy = 6 / (2 * np.tan(np.radians(20.0)))
    assert_close(K, torch.tensor([[fy, 0, 6.0], [0, fy, 2.5], [0, 0, 1]], dtype=torch.float64), atol=1e-4, what="K")
