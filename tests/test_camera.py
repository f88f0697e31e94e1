"""Camera: DESIGN conventions (K, world_to_camera, pixel centres), kornia round trip, shader focal."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from kornia.geometry.depth import depth_to_3d, depth_to_3d_v2

from torchvol.geometry.camera import Camera, Rays, strata_shape

DTYPES = [torch.float32, torch.float64]
RT_TOL = {torch.float32: 1e-5, torch.float64: 1e-12}


def _cams(dtype, width=7, height=5, **kw):
    """Three different cameras in one batch."""
    eye = torch.tensor([[0.0, 1.0, -5.0], [3.0, 2.0, 1.0], [-1.0, -2.0, 2.5]], dtype=dtype)
    target = torch.tensor([[0.0, 0.0, 0.0], [0.5, -0.5, 0.2], [0.0, 0.3, -1.0]], dtype=dtype)
    up = torch.tensor([0.0, 1.0, 0.0], dtype=dtype)
    if not kw:
        kw = dict(fov_y=torch.tensor([45.0, 60.0, 30.0], dtype=dtype))
    return Camera.look_at(eye, target, up, width=width, height=height, **kw)


def _shader_rd(eye, target, up, focal, W, H):
    """The seeds' GLSL camera, pixel by pixel (float64), as [H, W, 3] with row 0 the top."""
    eye, target, up = (torch.as_tensor(x, dtype=torch.float64) for x in (eye, target, up))
    ww = torch.nn.functional.normalize(target - eye, dim=0)
    uu = torch.nn.functional.normalize(torch.linalg.cross(ww, up), dim=0)
    vv = torch.linalg.cross(uu, ww)
    out = torch.empty(H, W, 3, dtype=torch.float64)
    for j in range(H):
        for i in range(W):
            frag = torch.tensor([i + 0.5, H - j - 0.5], dtype=torch.float64)  # GL: y up
            res = torch.tensor([W, H], dtype=torch.float64)
            p = (2 * frag - res) / res[1]
            out[j, i] = torch.nn.functional.normalize(p[0] * uu + p[1] * vv + focal * ww, dim=0)
    return out


# ---------------------------------------------------------------------------- K, world_to_camera
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("W,H", [(7, 5), (4, 9), (1, 1), (640, 480)])
def test_intrinsics_follow_design(dtype, W, H):
    fov = torch.tensor([45.0, 60.0, 30.0], dtype=dtype)
    cam = _cams(dtype, W, H, fov_y=fov)
    assert cam.K.shape == (3, 3, 3) and cam.K.dtype == dtype
    assert cam.world_to_camera.shape == (3, 4, 4) and cam.world_to_camera.dtype == dtype
    fy = H / (2 * torch.tan(torch.deg2rad(fov.double()) / 2))
    expect = torch.zeros(3, 3, 3, dtype=torch.float64)
    expect[:, 0, 0] = fy
    expect[:, 1, 1] = fy
    expect[:, 0, 2] = W / 2 - 0.5
    expect[:, 1, 2] = H / 2 - 0.5
    expect[:, 2, 2] = 1
    torch.testing.assert_close(cam.K.double(), expect, rtol=1e-6 if dtype == torch.float32 else 1e-14, atol=0)
    assert cam.batch_size == 3 and cam.width == W and cam.height == H


@pytest.mark.parametrize("dtype", DTYPES)
def test_extrinsics_rigid_and_axes(dtype):
    cam = _cams(dtype)
    tol = 1e-6 if dtype == torch.float32 else 1e-14
    R = cam.world_to_camera[:, :3, :3]
    eye3 = torch.eye(3, dtype=dtype).expand(3, 3, 3)
    torch.testing.assert_close(R @ R.transpose(-1, -2), eye3, atol=tol, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(3, dtype=dtype), atol=tol, rtol=0)
    bottom = torch.tensor([0, 0, 0, 1], dtype=dtype).expand(3, 4)
    assert torch.equal(cam.world_to_camera[:, 3], bottom)
    # eye maps to the camera origin, target to +z on the optical axis
    eye = torch.tensor([[0.0, 1.0, -5.0], [3.0, 2.0, 1.0], [-1.0, -2.0, 2.5]], dtype=dtype)
    target = torch.tensor([[0.0, 0.0, 0.0], [0.5, -0.5, 0.2], [0.0, 0.3, -1.0]], dtype=dtype)
    torch.testing.assert_close(cam.eye, eye, atol=10 * tol, rtol=0)
    pt = (cam.world_to_camera[:, :3, :3] @ target[..., None])[..., 0] + cam.world_to_camera[:, :3, 3]
    torch.testing.assert_close(pt[:, :2], torch.zeros(3, 2, dtype=dtype), atol=10 * tol, rtol=0)
    torch.testing.assert_close(pt[:, 2], torch.linalg.vector_norm(target - eye, dim=-1), atol=10 * tol, rtol=0)
    # world up projects to camera -y (OpenCV y down); forward is camera +z
    up_cam = (R @ torch.tensor([0.0, 1.0, 0.0], dtype=dtype)[:, None])[..., 0]
    assert (up_cam[:, 1] < 0).all()
    torch.testing.assert_close(cam.forward, torch.nn.functional.normalize(target - eye, dim=-1), atol=tol, rtol=0)
    # camera_to_world is the inverse
    torch.testing.assert_close(
        cam.camera_to_world @ cam.world_to_camera, torch.eye(4, dtype=dtype).expand(3, 4, 4), atol=10 * tol, rtol=0
    )


def test_python_inputs_and_scalar_broadcast():
    cam = Camera.look_at([0, 1, -5], [0, 0, 0], [0, 1, 0], width=8, height=6, focal=1.5)
    assert cam.K.dtype == torch.get_default_dtype() and cam.batch_size == 1
    assert cam.K[0, 1, 1].item() == pytest.approx(1.5 * 3)
    cam2 = Camera.look_at(
        torch.tensor([[0.0, 1, -5], [1, 1, 1]], dtype=torch.float64), [0, 0, 0], [0, 1, 0],
        width=8, height=6, fov_y=[40.0, 50.0], roll=10.0,
    )
    assert cam2.batch_size == 2 and cam2.K.dtype == torch.float64


@pytest.mark.parametrize(
    "eye,target,up",
    [([0, 0, 0], [0, 0, 0], [0, 1, 0]), ([0, 0, 0], [0, 3, 0], [0, 1, 0]), ([0, 0, 0], [0, -2, 0], [0, 1, 0]),
     ([0, 0, 0], [1, 0, 0], [0, 0, 0]), ([0, float("nan"), 0], [1, 0, 0], [0, 1, 0])],
)
def test_degenerate_raises(eye, target, up):
    with pytest.raises(ValueError):
        Camera.look_at(eye, target, up, width=4, height=4, fov_y=45.0)


def test_exactly_one_of_fov_and_focal():
    with pytest.raises(ValueError):
        Camera.look_at([0, 0, -1], [0, 0, 0], [0, 1, 0], width=4, height=4)
    with pytest.raises(ValueError):
        Camera.look_at([0, 0, -1], [0, 0, 0], [0, 1, 0], width=4, height=4, fov_y=45.0, focal=1.5)


# ---------------------------------------------------------------------------- rays
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("W,H,spp", [(7, 5, 1), (4, 9, 1), (3, 2, 4), (5, 3, 6)])
def test_ray_layout(dtype, W, H, spp):
    cam = _cams(dtype, W, H)
    rays = cam.rays(spp=spp, generator=torch.Generator().manual_seed(1))
    R = 3 * H * W * spp
    assert isinstance(rays, Rays) and len(rays) == R
    assert rays.origins.shape == (R, 3) and rays.directions.shape == (R, 3)
    assert rays.directions.dtype == dtype and rays.forward_cos.dtype == dtype
    assert rays.scene_index.dtype == torch.long and rays.pixel.dtype == torch.long
    torch.testing.assert_close(
        torch.linalg.vector_norm(rays.directions, dim=-1), torch.ones(R, dtype=dtype), atol=RT_TOL[dtype], rtol=0
    )
    # scene-major, then row, column, sub-sample
    b, j, i, s = torch.meshgrid(torch.arange(3), torch.arange(H), torch.arange(W), torch.arange(spp), indexing="ij")
    assert torch.equal(rays.scene_index, b.reshape(-1))
    assert torch.equal(rays.pixel[:, 0], i.reshape(-1))
    assert torch.equal(rays.pixel[:, 1], j.reshape(-1))
    torch.testing.assert_close(rays.origins, cam.eye[rays.scene_index], atol=0, rtol=0)
    fc = (rays.directions * cam.forward[rays.scene_index]).sum(-1)
    torch.testing.assert_close(rays.forward_cos, fc, atol=RT_TOL[dtype], rtol=0)
    chunks = list(rays.chunks(7))
    assert sum(len(c) for c in chunks) == R
    assert torch.equal(torch.cat([c.directions for c in chunks]), rays.directions)


@settings(max_examples=60, deadline=None)
@given(W=st.integers(1, 9), H=st.integers(1, 7), spp=st.sampled_from([1, 2, 4]), cut=st.tuples(st.floats(0, 1), st.floats(0, 1)),
       jitter=st.booleans())
def test_a_ray_range_is_the_same_slice_of_all_rays(W, H, spp, cut, jitter):
    """`ray_range` lays its rays on the grid of the image rows they lie in: any range, partial rows
    at either end, across scenes, is bitwise the same slice of the whole batch's rays."""
    cam = _cams(torch.float32, W, H)
    cam.K[:, 0, 1] = torch.tensor([0.0, 0.05, -0.1])  # a skew: the column term depends on the row
    n = 3 * H * W * spp
    start, stop = sorted(int(c * n) for c in cut)
    stop = max(stop, start + 1) if start < n else n
    offsets = torch.rand(n, 2, generator=torch.Generator().manual_seed(W * H + spp)) - 0.5 if jitter else None
    whole = cam.ray_range(0, n, spp=spp, offsets=offsets)
    part = cam.ray_range(start, stop, spp=spp, offsets=None if offsets is None else offsets[start:stop])
    for field in ("origins", "directions", "scene_index", "pixel", "forward_cos"):
        got, want = getattr(part, field), getattr(whole, field)[start:stop]
        assert got.dtype == want.dtype and torch.equal(got, want), f"{field} of rays {start}:{stop} of {n}"


@settings(max_examples=40, deadline=None)
@given(W=st.integers(1, 40), H=st.integers(1, 9), spp=st.sampled_from([1, 2, 4, 9]), scenes=st.sampled_from([1, 3]),
       cut=st.tuples(st.floats(0, 1), st.floats(0, 1)), jitter=st.booleans())
def test_the_kernel_rays_are_the_eager_rays(W, H, spp, scenes, cut, jitter):
    """`ray_range(kernel=True)` (`camera_ray` in one Dr.Jit kernel, each lane's scene, row, column
    and sub-sample from its index; one camera's values as parameters, several gathered) is bitwise
    the eager ray range: any range of one or several scenes, stratum centres or given offsets."""
    from torchvol.runtime.compilation import drjit_available

    if not drjit_available():
        pytest.skip("Dr.Jit's LLVM backend is not available here")
    cam = _cams(torch.float32, W, H)
    cam.K[:, 0, 1] = torch.tensor([0.0, 0.05, -0.1])
    cam = cam.select(list(range(scenes)))
    n = scenes * H * W * spp
    start, stop = sorted(int(c * n) for c in cut)
    stop = max(stop, start + 1) if start < n else n
    offsets = torch.rand(stop - start, 2, generator=torch.Generator().manual_seed(n)) - 0.5 if jitter else None
    eager = cam.ray_range(start, stop, spp=spp, offsets=offsets)
    kernel = cam.ray_range(start, stop, spp=spp, offsets=offsets, kernel=True)
    for field in ("origins", "directions", "scene_index", "pixel", "forward_cos"):
        got, want = getattr(kernel, field), getattr(eager, field)
        differ = got != want
        bad = (differ if differ.ndim == 1 else differ.any(1)).nonzero()  # (an empty range too)
        assert got.shape == want.shape and not len(bad), (
            f"{field} of rays {start}:{stop} of {n}: {len(bad)} differ, first at {bad[:1].tolist()}: "
            f"{got[bad[0]].tolist() if len(bad) else ''} vs {want[bad[0]].tolist() if len(bad) else ''}"
        )


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("W,H", [(7, 5), (6, 11), (16, 16)])
def test_spp1_rays_pass_through_pixel_centres(dtype, W, H):
    cam = _cams(dtype, W, H)
    rays = cam.rays()
    for t in (0.5, 3.0):
        pts = rays.origins + t * rays.directions
        proj = cam.project(pts, rays.scene_index)
        tol = 2e-4 if dtype == torch.float32 else 1e-10
        torch.testing.assert_close(proj[:, :2], rays.pixel.to(dtype), atol=tol, rtol=0)
        torch.testing.assert_close(proj[:, 2], t * rays.forward_cos, atol=RT_TOL[dtype] * 10, rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("W,H", [(7, 5), (4, 9)])
def test_kornia_depth_to_3d_round_trip(dtype, W, H):
    """depth = t * forward_cos unprojected by kornia and mapped by inv(world_to_camera) = o + t d."""
    cam = _cams(dtype, W, H)
    rays = cam.rays()
    B = cam.batch_size
    g = torch.Generator().manual_seed(0)
    t = (1.0 + 4.0 * torch.rand(B * H * W, generator=g, dtype=torch.float64)).to(dtype)
    expected = (rays.origins + t[:, None] * rays.directions).reshape(B, H, W, 3)
    depth = (t * rays.forward_cos).reshape(B, 1, H, W)
    pc = depth_to_3d(depth, cam.K)  # (B, 3, H, W), camera frame
    pc_v2 = depth_to_3d_v2(depth[:, 0], cam.K)  # (B, H, W, 3)
    torch.testing.assert_close(pc.permute(0, 2, 3, 1), pc_v2, atol=RT_TOL[dtype], rtol=0)
    c2w = torch.linalg.inv(cam.world_to_camera)
    pw = torch.einsum("bij,bhwj->bhwi", c2w[:, :3, :3], pc_v2) + c2w[:, None, None, :3, 3]
    torch.testing.assert_close(pw, expected, atol=RT_TOL[dtype], rtol=0)


@pytest.mark.parametrize("W,H", [(7, 5), (4, 9), (1, 1), (8, 2)])
@pytest.mark.parametrize("dtype", DTYPES)
def test_shader_focal_matches_glsl(W, H, dtype):
    eyes = [[0.0, 1.0, -5.0], [2.0, 0.5, 3.0]]
    targets = [[0.0, 0.0, 0.0], [0.0, -1.0, 0.0]]
    focals = [1.5, 0.8]
    cam = Camera.look_at(
        torch.tensor(eyes, dtype=dtype), torch.tensor(targets, dtype=dtype), torch.tensor([0.0, 1.0, 0.0], dtype=dtype),
        width=W, height=H, focal=torch.tensor(focals, dtype=dtype),
    )
    rd = cam.rays().directions.reshape(2, H, W, 3)
    for b in range(2):
        ref = _shader_rd(eyes[b], targets[b], [0, 1, 0], focals[b], W, H)
        tol = 1e-6 if dtype == torch.float32 else 1e-14
        torch.testing.assert_close(rd[b].double(), ref, atol=tol, rtol=0)


def test_template_camera_matrix_form():
    """The template's ``rd = ca * normalize(vec3(p, 1.5))`` with ``setCamera(ro, ta, cr)``."""
    W, H = 9, 6
    ro = torch.tensor([1.0, 1.5, -4.0], dtype=torch.float64)
    ta = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)
    cam = Camera.look_at(ro, ta, [0.0, 1.0, 0.0], width=W, height=H, focal=1.5)
    cw = torch.nn.functional.normalize(ta - ro, dim=0)
    cu = torch.nn.functional.normalize(torch.linalg.cross(cw, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)), dim=0)
    cv = torch.nn.functional.normalize(torch.linalg.cross(cu, cw), dim=0)
    ca = torch.stack([cu, cv, cw], dim=1)  # GLSL mat3(cu, cv, cw): columns
    rd = cam.rays().directions.reshape(H, W, 3)
    for j in range(H):
        for i in range(W):
            p = (2 * torch.tensor([i + 0.5, H - j - 0.5], dtype=torch.float64) - torch.tensor([W, H])) / H
            ref = ca @ torch.nn.functional.normalize(torch.cat([p, torch.tensor([1.5], dtype=torch.float64)]), dim=0)
            torch.testing.assert_close(rd[j, i], ref, atol=1e-13, rtol=0)


@pytest.mark.parametrize("fov", [20.0, 45.0, 67.38, 90.0, 120.0])
def test_fov_focal_equivalence(fov):
    a = Camera.look_at([0.0, 1, -5], [0.0, 0, 0], [0.0, 1, 0], width=10, height=7, fov_y=torch.tensor([fov], dtype=torch.float64))
    f = 1.0 / math.tan(math.radians(fov) / 2)
    b = Camera.look_at([0.0, 1, -5], [0.0, 0, 0], [0.0, 1, 0], width=10, height=7, focal=torch.tensor([f], dtype=torch.float64))
    torch.testing.assert_close(a.K, b.K, atol=1e-12, rtol=0)
    torch.testing.assert_close(a.rays().directions, b.rays().directions, atol=1e-13, rtol=0)
    # the top edge of the picture (row -0.5) is fov/2 above the axis
    fy, cy = a.K[0, 1, 1].item(), a.K[0, 1, 2].item()
    assert math.degrees(math.atan((cy + 0.5) / fy)) * 2 == pytest.approx(fov, abs=1e-9)


def test_roll_rotates_about_forward():
    eye, target, up = [0.0, 0.0, -3.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0]
    base = Camera.look_at(eye, target, up, width=8, height=8, fov_y=60.0)
    for roll in (30.0, -75.0, 90.0):
        cam = Camera.look_at(eye, target, up, width=8, height=8, fov_y=60.0, roll=roll)
        torch.testing.assert_close(cam.forward, base.forward)
        torch.testing.assert_close(cam.eye, base.eye, atol=1e-6, rtol=0)
        R0, R1 = base.world_to_camera[0, :3, :3], cam.world_to_camera[0, :3, :3]
        rel = R1 @ R0.T  # rotation about camera z
        r = math.radians(roll)
        # camera x' = cos r x + sin r (screen up = -y); in OpenCV camera coords: (cos r, -sin r, 0)
        expect = torch.tensor([[math.cos(r), -math.sin(r), 0], [math.sin(r), math.cos(r), 0], [0, 0, 1.0]])
        torch.testing.assert_close(rel, expect, atol=1e-6, rtol=0)
        assert torch.linalg.det(R1).item() == pytest.approx(1.0, abs=1e-6)
    # matches the template's setCamera(ro, ta, cr): up = (sin cr, cos cr, 0), for a view along z
    cr = 0.3
    cw = torch.tensor([0.0, 0.0, 1.0])
    cu = torch.nn.functional.normalize(torch.linalg.cross(cw, torch.tensor([math.sin(cr), math.cos(cr), 0.0])), dim=0)
    cam = Camera.look_at(eye, target, up, width=8, height=8, fov_y=60.0, roll=math.degrees(cr))
    torch.testing.assert_close(cam.world_to_camera[0, 0, :3], cu, atol=1e-6, rtol=0)
    # a +90 degree roll turns the camera's right axis into its former up axis (world +y here)
    cam90 = Camera.look_at(eye, target, up, width=8, height=8, fov_y=60.0, roll=90.0)
    torch.testing.assert_close(cam90.world_to_camera[0, 0, :3], torch.tensor([0.0, 1.0, 0.0]), atol=1e-6, rtol=0)


@pytest.mark.parametrize("spp", [2, 4, 6, 9, 16])
def test_stratified_subsamples(spp):
    nx, ny = strata_shape(spp)
    assert nx * ny == spp and nx >= ny
    cam = _cams(torch.float64, 5, 4)
    centred = cam.rays(spp=spp)
    single = cam.rays(spp=1)
    # generator=None: stratum centres, symmetric -> projected mean is the pixel centre
    for rays in (centred, cam.rays(spp=spp, generator=torch.Generator().manual_seed(3))):
        pts = rays.origins + 2.0 * rays.directions
        proj = cam.project(pts, rays.scene_index)[:, :2]
        off = proj - rays.pixel.double()
        assert (off.abs() < 0.5).all(), "sub-sample left its pixel"
        # each sub-sample stays inside its stratum
        s = torch.arange(len(rays)) % spp
        sx, sy = (s % nx).double(), (s // nx).double()
        assert ((off[:, 0] + 0.5) >= sx / nx - 1e-9).all() and ((off[:, 0] + 0.5) <= (sx + 1) / nx + 1e-9).all()
        assert ((off[:, 1] + 0.5) >= sy / ny - 1e-9).all() and ((off[:, 1] + 0.5) <= (sy + 1) / ny + 1e-9).all()
    mean = (cam.project(centred.origins + 2.0 * centred.directions, centred.scene_index)[:, :2]).reshape(-1, spp, 2).mean(1)
    torch.testing.assert_close(mean, single.pixel.double(), atol=1e-9, rtol=0)
    # the jitter is reproducible from the generator
    a = cam.rays(spp=spp, generator=torch.Generator().manual_seed(7)).directions
    b = cam.rays(spp=spp, generator=torch.Generator().manual_seed(7)).directions
    assert torch.equal(a, b)


def test_batch_of_different_cameras_is_per_scene():
    cam = _cams(torch.float64, 6, 4)
    rays = cam.rays()
    for b in range(cam.batch_size):
        one = cam.select(b).rays()
        m = rays.scene_index == b
        torch.testing.assert_close(rays.directions[m], one.directions, atol=0, rtol=0)
        torch.testing.assert_close(rays.origins[m], one.origins, atol=0, rtol=0)


def test_direct_construction_and_non_square():
    K = torch.tensor([[[100.0, 0, 10.5], [0, 80.0, 3.5], [0, 0, 1]]], dtype=torch.float64)
    w2c = torch.eye(4, dtype=torch.float64)[None]
    cam = Camera(K=K, world_to_camera=w2c, width=22, height=8)
    rays = cam.rays()
    d = rays.directions.reshape(8, 22, 3)
    # row 0 is the top: camera y down = world y down for the identity pose
    assert d[0, 0, 1] < 0 and d[-1, 0, 1] > 0 and d[0, 0, 0] < 0 and d[0, -1, 0] > 0
    x = (torch.arange(22, dtype=torch.float64) - 10.5) / 100.0
    y = (torch.arange(8, dtype=torch.float64) - 3.5) / 80.0
    ref = torch.nn.functional.normalize(
        torch.stack(torch.broadcast_tensors(x[None, :], y[:, None], torch.ones(8, 22, dtype=torch.float64)), -1), dim=-1
    )
    torch.testing.assert_close(d, ref, atol=1e-15, rtol=0)
