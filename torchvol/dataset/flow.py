"""Optical flow of static geometry from depth and two camera poses (kornia).

Conventions are torchvol's (DESIGN.md, `camera.py`): depth is planar z along the camera's forward
axis, 0 where nothing was hit; `K` in pixels with pixel centres at integer coordinates (column i,
row j at (i, j)); `world_to_camera` rigid, OpenCV axes (x right, y down, z forward).

The flow at pixel (i, j) of frame a is where the depth point seen there projects in frame b, minus
(i, j): `flow = π(K_b · T_ab · unproject(depth, K_a)) − (i, j)`, in pixels, x (columns) then y
(rows). It follows the camera's motion only: a point is assumed not to move in the world (media
drifting with the wind are not followed).
"""

from __future__ import annotations

import torch
from kornia.geometry.camera import project_points
from kornia.geometry.depth import depth_to_3d_v2
from kornia.geometry.linalg import (
    compose_transformations,
    inverse_transformation,
    transform_points,
)
from torch import Tensor

__all__ = ["flow_from_depth"]

# a point must lie this far in front of camera b (relative to its depth in a) to be projected
_MIN_Z = 1e-6


def flow_from_depth(depth: Tensor, K: Tensor, world_to_camera_a: Tensor, world_to_camera_b: Tensor, *,
                    K_b: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Forward flow from camera a to camera b of the points at `depth` seen by camera a.

    depth             (B, 1, H, W) planar z in camera a, 0 (or inf/NaN) where nothing was hit
    K                 (B, 3, 3) intrinsics of camera a (zero skew), and of b unless `K_b` is given
    world_to_camera_a (B, 4, 4), world_to_camera_b (B, 4, 4) rigid poses
    -> flow (B, 2, H, W) in pixels (dx, dy), the dtype of `depth`, NaN-free;
       valid (B, 1, H, W) bool: depth finite and > 0, and the point in front of camera b.
       Invalid pixels have flow 0. A valid point may project outside the picture of b.
    """
    if depth.ndim != 4 or depth.shape[1] != 1:
        raise ValueError(f"flow_from_depth: depth must be (B, 1, H, W), got {tuple(depth.shape)}")
    B = depth.shape[0]
    K_b = K if K_b is None else K_b
    for name, t, shape in (("K", K, (B, 3, 3)), ("K_b", K_b, (B, 3, 3)),
                           ("world_to_camera_a", world_to_camera_a, (B, 4, 4)),
                           ("world_to_camera_b", world_to_camera_b, (B, 4, 4))):
        if tuple(t.shape) != shape:
            raise ValueError(f"flow_from_depth: {name} must be {shape}, got {tuple(t.shape)}")
    if (K[:, 0, 1] != 0).any():
        raise ValueError("flow_from_depth: K must have zero skew (kornia's unprojection ignores it)")
    dtype = depth.dtype
    z = depth[:, 0]
    hit = torch.isfinite(z) & (z > 0)
    z = torch.where(hit, z, torch.ones_like(z))  # any finite depth: masked below
    K, K_b = K.to(dtype), K_b.to(dtype)
    points_a = depth_to_3d_v2(z, K)  # (B, H, W, 3) in camera a
    # camera a -> world -> camera b: world_to_camera_b · world_to_camera_a⁻¹
    a_to_b = compose_transformations(world_to_camera_b.to(dtype), inverse_transformation(world_to_camera_a.to(dtype)))
    points_b = transform_points(a_to_b[:, None], points_a)  # (B, H, W, 3) in camera b
    front = points_b[..., 2] > _MIN_Z * z
    valid = hit & front
    # points behind camera b are masked; give them z = 1 so the projection stays finite
    safe = torch.where(front[..., None], points_b, torch.ones_like(points_b))
    pixels_b = project_points(safe, K_b[:, None, None])  # (B, H, W, 2)
    H, W = z.shape[-2:]
    rows, cols = torch.meshgrid(torch.arange(H, dtype=dtype, device=depth.device),
                                torch.arange(W, dtype=dtype, device=depth.device), indexing="ij")
    flow = pixels_b - torch.stack([cols, rows], dim=-1)
    flow = torch.where(valid[..., None], flow, torch.zeros_like(flow))
    return flow.permute(0, 3, 1, 2).contiguous(), valid[:, None]
