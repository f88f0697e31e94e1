"""Pinhole camera in OpenCV/kornia conventions, and the flat primary-ray bundle.

Conventions (normative, see ``shared/DESIGN.md``):

* World: right-handed, y up.
* Camera axes (OpenCV): x right, y down, z forward. ``world_to_camera`` (B, 4, 4) maps world points
  to camera points; ``K`` (B, 3, 3) maps camera points to pixels with *integer* pixel centres
  (column ``i`` covers ``[i - 0.5, i + 0.5]``), row 0 the top of the picture.
* ``fov_y`` is the full vertical field of view in degrees: ``fy = H / (2 tan(fov_y / 2))``.
* Shader focal ``f`` (the seeds' ``rd = normalize(p.x*u + p.y*v + f*w)`` with
  ``p = (2*fragCoord - res) / res.y``): ``fx = fy = f * H / 2``. Hence ``f = 1 / tan(fov_y / 2)``.
* Principal point of :meth:`Camera.look_at`: ``cx = W/2 - 0.5``, ``cy = H/2 - 0.5``.

Shapes follow ``docs/ARCHITECTURE.md``: ``B`` scenes, ``R = B*H*W*spp`` flat rays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterator, Sequence

import torch
from torch import Tensor

from ..ops import lanes
from ..ops.mathops import take_rows

__all__ = ["Camera", "Rays", "camera_ray", "strata_shape"]


def camera_ray(px, py, k: Sequence, r: Sequence) -> list:
    """The ray through image point (px, py) (lanes, `ops.lanes`: torch tensors or a kernel's) of a
    camera with intrinsics k = (fx, skew, cx, fy, cy) and rotation R (r: its nine entries,
    row-major), each lanes or numbers: camera-space ((x − cx − s·y') / fx, y', 1) with
    y' = (y − cy) / fy (K⁻¹ in closed form), world R^T d normalised, and its cosine to the camera's
    forward axis -> [dx, dy, dz, forward_cos]. Written out with correctly rounded square roots (not
    torch's norm, rsqrt or float32 sqrt, whose roundings a kernel does not share): eager and kernel
    rays are the same bits."""
    fx, skew, cx, fy, cy = k
    yc = (py - cy) / fy
    xc = (px - cx - skew * yc) / fx
    d = [xc * r[c] + yc * r[3 + c] + r[6 + c] for c in range(3)]  # d^T R: (R^T d)^T, d_z = 1
    norm = lanes.sqrt_rounded(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    return [d[0] / norm, d[1] / norm, d[2] / norm, 1.0 / lanes.sqrt_rounded(xc * xc + yc * yc + 1.0)]


@dataclass(frozen=True)
class Rays:
    """A flat bundle of rays.

    origins     [R, 3]  ray origins (the camera eye for primary rays)
    directions  [R, 3]  unit directions
    scene_index [R]     long, index into per-scene tensors (B, ...)
    pixel       [R, 2]  long, (column, row), row 0 the top of the picture
    forward_cos [R]     dot(direction, camera forward); planar depth z = t * forward_cos
    """

    origins: Tensor
    directions: Tensor
    scene_index: Tensor
    pixel: Tensor
    forward_cos: Tensor

    def __len__(self) -> int:
        return int(self.origins.shape[0])

    @property
    def num_rays(self) -> int:
        """R, the number of rays."""
        return int(self.origins.shape[0])

    @property
    def dtype(self) -> torch.dtype:
        """The rays' floating dtype."""
        return self.origins.dtype

    @property
    def device(self) -> torch.device:
        """The rays' device."""
        return self.origins.device

    def slice(self, start: int, stop: int) -> "Rays":
        """Rays ``start:stop`` (views, no copy)."""
        return Rays(
            origins=self.origins[start:stop],
            directions=self.directions[start:stop],
            scene_index=self.scene_index[start:stop],
            pixel=self.pixel[start:stop],
            forward_cos=self.forward_cos[start:stop],
        )

    def chunks(self, size: int) -> Iterator["Rays"]:
        """Consecutive slices of at most ``size`` rays, in order (views, no copy)."""
        if size <= 0:
            raise ValueError(f"chunk size must be positive, got {size}")
        n = self.num_rays
        for start in range(0, n, size):
            yield self.slice(start, min(start + size, n))

    def repeat(self, times: int) -> "Rays":
        """The rays `times` over, one copy after another ([times·R]; a copy, ~13× faster than
        `select` of the repeated indices)."""
        if times == 1:
            return self
        return Rays(
            origins=self.origins.repeat(times, 1),
            directions=self.directions.repeat(times, 1),
            scene_index=self.scene_index.repeat(times),
            pixel=self.pixel.repeat(times, 1),
            forward_cos=self.forward_cos.repeat(times),
        )

    def select(self, mask_or_index: Tensor) -> "Rays":
        """Rays picked by a boolean mask ``[R]`` or a long index ``[N]``."""
        return Rays(
            origins=self.origins[mask_or_index],
            directions=self.directions[mask_or_index],
            scene_index=self.scene_index[mask_or_index],
            pixel=self.pixel[mask_or_index],
            forward_cos=self.forward_cos[mask_or_index],
        )


def strata_shape(spp: int) -> tuple[int, int]:
    """``(nx, ny)`` strata per pixel, ``nx * ny == spp``, as square as possible, ``nx >= ny``.

    E.g. 1 -> (1, 1), 2 -> (2, 1), 4 -> (2, 2), 6 -> (3, 2), 8 -> (4, 2), 16 -> (4, 4), 7 -> (7, 1).
    """
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    ny = int(math.isqrt(spp))
    while spp % ny:
        ny -= 1
    return spp // ny, ny


def _float_dtype(*values) -> tuple[torch.dtype, torch.device]:
    """Floating dtype and device implied by the tensor arguments (default dtype, CPU otherwise)."""
    dtype = None
    device = None
    for v in values:
        if isinstance(v, Tensor):
            if device is None:
                device = v.device
            if v.is_floating_point():
                dtype = v.dtype if dtype is None else torch.promote_types(dtype, v.dtype)
    if dtype is None:
        dtype = torch.get_default_dtype()
    return dtype, (device if device is not None else torch.device("cpu"))


def _vec3(x, dtype, device) -> Tensor:
    t = torch.as_tensor(x, dtype=dtype, device=device)
    if t.ndim == 1:
        t = t[None]
    if t.ndim != 2 or t.shape[-1] != 3:
        raise ValueError(f"expected a 3-vector or [B, 3], got shape {tuple(t.shape)}")
    return t


def _per_scene(x, B: int, dtype, device) -> Tensor:
    t = torch.as_tensor(x, dtype=dtype, device=device)
    if t.ndim == 0:
        t = t.expand(B)
    if t.ndim != 1 or t.shape[0] not in (1, B):
        raise ValueError(f"expected a scalar or [B={B}], got shape {tuple(t.shape)}")
    return t.expand(B)


def _look_at_rotation(eye: Tensor, target: Tensor, up: Tensor, roll) -> Tensor:
    """`Camera.look_at`'s world -> camera rotation from `eye`, `target`, `up` [B, 3] and `roll`
    (degrees, scalar or [B]): (B, 3, 3), rows (u', -v', w). Raises ValueError where the basis is undefined."""
    fwd = target - eye
    fwd_len = torch.linalg.vector_norm(fwd, dim=-1)
    if (fwd_len == 0).any():
        raise ValueError("Camera.look_at: eye and target coincide; the view direction is undefined")
    w = fwd / fwd_len[:, None]
    up_len = torch.linalg.vector_norm(up, dim=-1)
    if (up_len == 0).any():
        raise ValueError("Camera.look_at: up vector is zero")
    right = torch.linalg.cross(w, up, dim=-1)
    right_len = torch.linalg.vector_norm(right, dim=-1)
    # |cross(w, up)| / |up| = sin(angle between view and up).
    if (right_len <= 16 * torch.finfo(eye.dtype).eps * up_len).any():
        raise ValueError("Camera.look_at: up vector is parallel to the view direction")
    u = right / right_len[:, None]
    v = torch.linalg.cross(u, w, dim=-1)

    r = torch.deg2rad(_per_scene(roll, eye.shape[0], eye.dtype, eye.device))
    cr, sr = torch.cos(r)[:, None], torch.sin(r)[:, None]
    u, v = cr * u + sr * v, cr * v - sr * u
    return torch.stack([u, -v, w], dim=-2)  # (B, 3, 3) rows: camera x, y, z in world


def _intrinsics(B: int, width: int, height: int, *, fov_y, focal, dtype, device) -> Tensor:
    """`Camera.look_at`'s K (B, 3, 3) from `fov_y` (degrees) or the shader `focal` (scalar or [B]):
    fx = fy, the principal point at the image centre."""
    if fov_y is not None:
        half = torch.deg2rad(_per_scene(fov_y, B, dtype, device)) / 2
        fy = height / (2 * torch.tan(half))
    else:
        fy = _per_scene(focal, B, dtype, device) * (height / 2)
    K = torch.zeros(B, 3, 3, dtype=dtype, device=device)
    K[:, 0, 0] = fy
    K[:, 1, 1] = fy
    K[:, 0, 2] = width / 2 - 0.5
    K[:, 1, 2] = height / 2 - 0.5
    K[:, 2, 2] = 1
    return K


@dataclass(frozen=True)
class Camera:
    """Pinhole cameras for a batch of B scenes (OpenCV axes: x right, y down, z forward).

    K               (B, 3, 3)  intrinsics in pixels, integer pixel centres
    world_to_camera (B, 4, 4)  rigid world -> camera transform
    width, height   image size in pixels (shared by the batch)
    """

    K: Tensor
    world_to_camera: Tensor
    width: int
    height: int

    # ------------------------------------------------------------------ properties
    @property
    def batch_size(self) -> int:
        """B, the number of cameras (one a scene)."""
        return int(self.K.shape[0])

    @property
    def dtype(self) -> torch.dtype:
        """The cameras' floating dtype."""
        return self.K.dtype

    @property
    def device(self) -> torch.device:
        """The cameras' device."""
        return self.K.device

    @property
    def rotation(self) -> Tensor:
        """(B, 3, 3) world -> camera rotation R (rows: camera x, y, z axes in world)."""
        return self.world_to_camera[:, :3, :3]

    @property
    def camera_to_world(self) -> Tensor:
        """(B, 4, 4) inverse of ``world_to_camera``, via R^T (the transform is rigid)."""
        R = self.rotation
        t = self.world_to_camera[:, :3, 3]
        Rt = R.transpose(-1, -2)
        out = torch.zeros_like(self.world_to_camera)
        out[:, :3, :3] = Rt
        out[:, :3, 3] = -(Rt @ t[..., None])[..., 0]
        out[:, 3, 3] = 1
        return out

    @property
    def eye(self) -> Tensor:
        """(B, 3) camera centre in world coordinates: -R^T t."""
        R = self.rotation
        t = self.world_to_camera[:, :3, 3]
        return -(R.transpose(-1, -2) @ t[..., None])[..., 0]

    @property
    def forward(self) -> Tensor:
        """(B, 3) camera +z (viewing direction) in world coordinates: the third row of R."""
        return self.rotation[:, 2, :]

    # ------------------------------------------------------------------ construction
    @classmethod
    def look_at(
        cls,
        eye,
        target,
        up,
        *,
        width: int,
        height: int,
        fov_y=None,
        focal=None,
        roll=0.0,
    ) -> "Camera":
        """Cameras at ``eye`` [B,3] looking at ``target`` [B,3] with ``up`` [B,3] (3-vectors broadcast).

        Exactly one of ``fov_y`` (degrees, full vertical FOV, scalar or [B]) and ``focal`` (the seeds'
        shader focal length, scalar or [B]; fy = fx = focal * H / 2) must be given.

        Basis as in the seeds: ``w = normalize(target - eye)`` (forward),
        ``u = normalize(cross(w, up))`` (screen right), ``v = cross(u, w)`` (screen up).
        ``roll`` (degrees, scalar or [B]) rotates the camera about ``w``:
        ``u' = cos(r) u + sin(r) v``, ``v' = -sin(r) u + cos(r) v`` — positive roll turns the camera's
        right/up axes counter-clockwise as drawn on the screen (u right, v up), so the *picture*
        content turns clockwise. This equals the seeds' ``setCamera(ro, ta, cr)`` with
        ``cr = radians(roll)`` when ``up = (0,1,0)`` and the view is along world z.

        Camera axes (OpenCV): x = u', y = -v', z = w; ``world_to_camera = [[R, -R eye], [0, 1]]`` with
        R's rows (u', -v', w) (det R = +1). ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``,
        ``cx = W/2 - 0.5``, ``cy = H/2 - 0.5``.

        Math happens in the floating dtype of the tensor arguments (default dtype for python
        numbers) on their device. Raises ``ValueError`` for non-finite input, eye == target, or an
        up vector parallel to the view direction (a last guard; the scene layer validates first).
        """
        if (fov_y is None) == (focal is None):
            raise ValueError("Camera.look_at: give exactly one of fov_y and focal")
        width, height = int(width), int(height)
        if width < 1 or height < 1:
            raise ValueError(f"Camera.look_at: image size must be positive, got {width}x{height}")
        dtype, device = _float_dtype(eye, target, up, fov_y, focal, roll)
        eye_t, target_t, up_t = torch.broadcast_tensors(
            _vec3(eye, dtype, device), _vec3(target, dtype, device), _vec3(up, dtype, device)
        )
        B = eye_t.shape[0]
        for name, v in (("eye", eye_t), ("target", target_t), ("up", up_t)):
            if not torch.isfinite(v).all():
                raise ValueError(f"Camera.look_at: {name} must be finite, got {v.tolist()}")

        R = _look_at_rotation(eye_t, target_t, up_t, roll)
        w2c = torch.zeros(B, 4, 4, dtype=dtype, device=device)
        w2c[:, :3, :3] = R
        w2c[:, :3, 3] = -(R @ eye_t[..., None])[..., 0]
        w2c[:, 3, 3] = 1
        K = _intrinsics(B, width, height, fov_y=fov_y, focal=focal, dtype=dtype, device=device)
        return cls(K=K, world_to_camera=w2c, width=width, height=height)

    # ------------------------------------------------------------------ rays
    def subpixel_offsets(self, spp: int, generator: torch.Generator | None = None) -> Tensor:
        """Sub-pixel offsets in (-0.5, 0.5): ``[spp, 2]`` (x, y) without generator (stratum centres),
        ``[B, H, W, spp, 2]`` with one (uniform jitter inside each stratum).

        Strata: ``(nx, ny) = strata_shape(spp)``; sub-sample ``s = sy * nx + sx`` (row-major, top
        row first). The jitter is drawn as one ``torch.rand((B, H, W, spp, 2), float64)`` call from
        ``generator`` on the generator's device, so it is reproducible across dtypes and processes.
        """
        nx, ny = strata_shape(spp)
        dtype, device = self.dtype, self.device
        sy, sx = torch.meshgrid(
            torch.arange(ny, dtype=torch.float64), torch.arange(nx, dtype=torch.float64), indexing="ij"
        )
        base = torch.stack([sx.reshape(-1), sy.reshape(-1)], dim=-1)  # [spp, 2]
        scale = torch.tensor([nx, ny], dtype=torch.float64)
        if spp == 1:
            return torch.zeros(1, 2, dtype=dtype, device=device)
        if generator is None:
            off = (base + 0.5) / scale - 0.5
        else:
            shape = (self.batch_size, self.height, self.width, spp, 2)
            xi = torch.rand(shape, generator=generator, dtype=torch.float64, device=generator.device)
            off = (base + xi.cpu()) / scale - 0.5
        off = off.to(dtype=dtype, device=device)
        lo = torch.nextafter(torch.tensor(-0.5, dtype=dtype), torch.tensor(0.0, dtype=dtype)).item()
        hi = torch.nextafter(torch.tensor(0.5, dtype=dtype), torch.tensor(0.0, dtype=dtype)).item()
        return off.clamp(lo, hi)

    def rays(self, *, spp: int = 1, generator: torch.Generator | None = None) -> Rays:
        """Primary rays, ``R = B*H*W*spp``, ordered scene-major, then row, column, sub-sample.

        Pixel (column i, row j) shoots through image point ``(i + dx, j + dy)``: the exact pixel
        centre for ``spp == 1``; stratified offsets (see :meth:`subpixel_offsets`) for ``spp > 1``.
        Camera-space direction ``((x - cx - s*y') / fx, y', 1)`` with ``y' = (y - cy) / fy``
        (closed form of K^-1, skew ``s = K[0,1]`` normally 0), world direction ``R^T d``,
        normalised. ``forward_cos = d_z / |d|``.
        """
        B, H, W = self.batch_size, self.height, self.width
        off = self.subpixel_offsets(spp, generator)
        n = B * H * W * spp
        off = off.reshape(-1, 2).repeat(n // off.reshape(-1, 2).shape[0], 1)  # [R, 2] in ray order
        return self.ray_range(0, n, spp=spp, offsets=off)

    def ray_range(self, start: int, stop: int, *, spp: int = 1, offsets: Tensor | None = None,
                  kernel: bool = False) -> Rays:
        """Rays ``start:stop`` of the flat order of :meth:`rays` (scene, row, column, sub-sample),
        built without the others: a renderer makes one chunk at a time, so memory stays bounded.

        offsets: ``[stop - start, 2]`` sub-pixel offsets (x, y) in (-0.5, 0.5); None gives the
        stratum centres (the pixel centre for spp == 1). kernel: the directions and forward_cos
        (`camera_ray`) made by one Dr.Jit kernel (float32, CPU), the same bits.
        """
        H, W = self.height, self.width
        device = self.device
        # the rays on a grid of the whole image rows they lie in (G rows of L = W·spp rays; at most
        # two rows only partly in the range): a row's scene, row index and camera broadcast along
        # it, not divided out of each ray's index and gathered per ray (two thirds of the time)
        L = W * spp
        g0 = start // L
        G, lo, hi = -(-stop // L) - g0, start - g0 * L, stop - g0 * L
        g = torch.arange(g0, g0 + G, device=device)
        b, row = g // H, g % H  # [G]
        lane = torch.arange(L, device=device)
        col, sample = lane // spp, lane % spp  # [L]
        ranged = lambda x: x.expand(G, L, *x.shape[2:]).reshape(G * L, *x.shape[2:])[lo:hi]  # noqa: E731
        if kernel and stop > start:
            directions, forward_cos = self._kernel_directions(g0, lo, stop - start, spp, offsets)
        else:
            directions, forward_cos = map(ranged, self._directions(b, row, col, sample, spp, offsets, (G, L, lo, hi)))
        return Rays(
            origins=ranged(take_rows(self.eye, b)[:, None]),
            directions=directions,
            scene_index=ranged(b[:, None]),
            pixel=ranged(torch.stack([col, 0 * col], 1)[None] + torch.stack([0 * row, row], 1)[:, None]),  # (column, row)
            forward_cos=forward_cos,
        )

    def _directions(self, b: Tensor, row: Tensor, col: Tensor, sample: Tensor, spp: int, offsets: Tensor | None,
                    grid: tuple[int, int, int, int]) -> tuple[Tensor, Tensor]:
        """`camera_ray` eagerly on the grid of image rows (b, row [G]; col, sample [L]; `grid` (G,
        L, lo, hi): the flat rays lo:hi of its G·L have `offsets`) -> directions (G, L, 3) and
        forward_cos (G, L)."""
        G, L, lo, hi = grid
        dtype = self.dtype
        if offsets is None:
            centres = self.subpixel_offsets(spp)  # [spp, 2]
            off = (centres[sample] if spp > 1 else centres.expand(L, 2))[None]  # [1, L, 2]
        else:
            off = offsets.new_zeros(G * L, 2)
            off[lo:hi] = offsets
            off = off.view(G, L, 2)
        px = col.to(dtype) + off[..., 0].to(dtype)  # [G or 1, L]
        py = row.to(dtype)[:, None] + off[..., 1].to(dtype)  # [G, L]
        k = take_rows(self.K.reshape(-1, 9)[:, [0, 1, 2, 4, 5]], b)[:, :, None].unbind(1)  # [G, 1] each
        r = take_rows(self.rotation.reshape(-1, 9), b)[:, :, None].unbind(1)  # R's rows, x, y, z
        *d, forward_cos = camera_ray(px, py, k, r)
        return torch.stack(d, -1), forward_cos

    def _kernel_directions(self, g0: int, lo: int, n: int, spp: int, offsets: Tensor | None) -> tuple[Tensor, Tensor]:
        """`camera_ray` of rays ``lo:lo + n`` of the grid of image rows from row ``g0`` as one Dr.Jit
        kernel, each lane's scene, row, column and sub-sample from its index (opaque sizes: one
        kernel for every image size and range) -> directions [n, 3], forward_cos [n]."""
        import drjit as dr
        from drjit.llvm import Array2f, Float, UInt32

        from ..ops.lanes import floats_of
        from ..runtime.compilation import traced_columns

        def kernel(_lane):
            W, H, P = (dr.opaque(UInt32, v) for v in (self.width, self.height, spp))
            local = dr.arange(UInt32, n) + dr.opaque(UInt32, lo)
            g = local // (W * P) + dr.opaque(UInt32, g0)
            b, lane = g // H, local % (W * P)
            row, col, sample = g - b * H, lane // P, lane % P
            if offsets is not None:
                off = dr.unravel(Array2f, floats_of(offsets.reshape(-1)))
            else:
                off = dr.gather(Array2f, floats_of(self.subpixel_offsets(spp).reshape(-1)), sample)
            px, py = Float(col) + off[0], Float(row) + off[1]
            K, R = self.K.reshape(-1, 9), self.rotation.reshape(-1, 9)  # each lane's camera gathered by its scene
            k = [dr.gather(Float, floats_of(K[:, j]), b) for j in (0, 1, 2, 4, 5)]
            r = [dr.gather(Float, floats_of(R[:, j]), b) for j in range(9)]
            return camera_ray(px, py, k, r)

        return traced_columns(kernel, self.K, (3, 1))

    # ------------------------------------------------------------------ helpers
    def project(self, points: Tensor, scene_index: Tensor | None = None) -> Tensor:
        """World points ``[N, 3]`` (of scene ``scene_index [N]``; all scene 0 if None) -> ``[N, 3]``
        (pixel x, pixel y, camera z)."""
        if scene_index is None:
            scene_index = torch.zeros(points.shape[0], dtype=torch.long, device=points.device)
        w2c = self.world_to_camera[scene_index]
        pc = (w2c[:, :3, :3] @ points[..., None])[..., 0] + w2c[:, :3, 3]
        K = self.K[scene_index]
        uvw = (K @ pc[..., None])[..., 0]
        return torch.stack([uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2], pc[:, 2]], dim=-1)

    def select(self, index: Sequence[int] | Tensor | int) -> "Camera":
        """The cameras of the given scenes (keeps the batch dimension)."""
        idx = torch.as_tensor(index, dtype=torch.long, device=self.K.device).reshape(-1)
        return Camera(self.K[idx], self.world_to_camera[idx], self.width, self.height)
