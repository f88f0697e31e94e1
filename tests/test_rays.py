"""Ray/box, ray/sphere, ray/slab: analytic chords, the 0*inf trap, and a dense-sampling oracle."""

import math

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchvol.geometry.rays import (
    clip_to_ray,
    intersect_box,
    intersect_slab,
    intersect_sphere,
)

DTYPES = [torch.float32, torch.float64]
INF = float("inf")


def _unit(v, dtype):
    v = torch.as_tensor(v, dtype=torch.float64)
    return (v / torch.linalg.vector_norm(v, dim=-1, keepdim=True)).to(dtype)


def _fibonacci(n, dtype):
    k = torch.arange(n, dtype=torch.float64) + 0.5
    phi = torch.acos(1 - 2 * k / n)
    theta = math.pi * (1 + 5**0.5) * k
    d = torch.stack([torch.cos(theta) * torch.sin(phi), torch.cos(phi), torch.sin(theta) * torch.sin(phi)], -1)
    return d.to(dtype)


def _no_nan(*ts):
    for t in ts:
        assert not torch.isnan(t).any(), "NaN in intersection result"


# ---------------------------------------------------------------------------- analytic chords
@pytest.mark.parametrize("dtype", DTYPES)
def test_sphere_chords_from_many_directions(dtype):
    d = _fibonacci(500, dtype)
    c = torch.tensor([0.3, -0.2, 0.5], dtype=dtype)
    r = 1.25
    # rays aimed at the centre from outside: chord 2r, entry at dist - r
    for dist in (3.0, 100.0):
        o = c - dist * d
        tn, tf = intersect_sphere(o, d, c, r)
        tol = 1e-5 * dist if dtype == torch.float32 else 1e-12 * dist
        torch.testing.assert_close(tn, torch.full_like(tn, dist - r), atol=tol, rtol=0)
        torch.testing.assert_close(tf, torch.full_like(tf, dist + r), atol=tol, rtol=0)
    # rays at impact parameter h: chord 2 sqrt(r^2 - h^2)
    perp = torch.linalg.cross(d, _unit([0.577, 0.21, -0.79], dtype).expand_as(d), dim=-1)
    perp = perp / torch.linalg.vector_norm(perp, dim=-1, keepdim=True)
    for h in (0.0, 0.5, 1.0, 1.2):
        o = c - 5 * d + h * perp
        tn, tf = intersect_sphere(o, d, c, r)
        half = math.sqrt(r * r - h * h)
        tol = 1e-5 if dtype == torch.float32 else 1e-12
        torch.testing.assert_close(tf - tn, torch.full_like(tn, 2 * half), atol=tol, rtol=0)
        torch.testing.assert_close((tn + tf) / 2, torch.full_like(tn, 5.0), atol=tol, rtol=0)
    # miss beyond the radius
    o = c - 5 * d + 1.3 * perp
    tn, tf = intersect_sphere(o, d, c, r)
    assert (tn > tf).all()
    # origin at the centre: (-r, r)
    tn, tf = intersect_sphere(c.expand_as(d), d, c, r)
    torch.testing.assert_close(tn, torch.full_like(tn, -r), atol=1e-6, rtol=0)
    torch.testing.assert_close(tf, torch.full_like(tf, r), atol=1e-6, rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_sphere_far_away_is_stable(dtype):
    """A tiny sphere seen from far: the naive b^2 - c cancels catastrophically; ours keeps the chord."""
    d = _unit([[0.0, 0.0, 1.0]], dtype)
    r = 0.01
    dist = 1e4 if dtype == torch.float32 else 1e7
    for h in (0.0, 0.006):
        o = torch.tensor([[h, 0.0, -dist]], dtype=dtype)
        tn, tf = intersect_sphere(o, d, [0.0, 0.0, 0.0], r)
        chord = 2 * math.sqrt(r * r - h * h)
        assert (tf - tn).item() == pytest.approx(chord, rel=0.05)


@pytest.mark.parametrize("dtype", DTYPES)
def test_box_chords_from_many_directions(dtype):
    lo = torch.tensor([-1.0, -0.5, -2.0], dtype=dtype)
    hi = torch.tensor([1.0, 1.5, 0.0], dtype=dtype)
    centre = (lo + hi) / 2
    half = (hi - lo) / 2
    d = _fibonacci(400, dtype)
    # from the centre: t_far = min_k half_k / |d_k|, t_near = -t_far
    tn, tf = intersect_box(centre.expand_as(d), d, lo, hi)
    expect = (half.double() / d.double().abs()).min(-1).values
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(tf.double(), expect, atol=tol, rtol=1e-6)
    torch.testing.assert_close(tn.double(), -expect, atol=tol, rtol=1e-6)
    # from outside towards the centre: same chord, shifted
    o = centre - 10 * d
    tn2, tf2 = intersect_box(o, d, lo, hi)
    tol = 1e-5 * 10 if dtype == torch.float32 else 1e-12 * 10
    torch.testing.assert_close(tn2.double(), 10 - expect, atol=tol, rtol=0)
    torch.testing.assert_close(tf2.double(), 10 + expect, atol=tol, rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_slab_chords(dtype):
    d = _fibonacci(300, dtype)
    d = d[d[:, 1].abs() > 1e-3]
    o = torch.tensor([0.3, 0.5, -1.0], dtype=dtype).expand_as(d)
    tn, tf = intersect_slab(o, d, -1.0, 2.0)
    y0 = (torch.tensor(-1.0, dtype=torch.float64) - 0.5) / d[:, 1].double()
    y1 = (torch.tensor(2.0, dtype=torch.float64) - 0.5) / d[:, 1].double()
    tol = 1e-4 if dtype == torch.float32 else 1e-10
    torch.testing.assert_close(tn.double(), torch.minimum(y0, y1), atol=0, rtol=tol)
    torch.testing.assert_close(tf.double(), torch.maximum(y0, y1), atol=0, rtol=tol)
    assert (tn < 0).all() and (tf > 0).all()


# ---------------------------------------------------------------------------- special cases
@pytest.mark.parametrize("dtype", DTYPES)
def test_box_axis_parallel_and_signed_zeros(dtype):
    lo, hi = [-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]
    rows = [  # origin, direction, expected (t_near, t_far) or None for a miss
        ([0.0, 0.0, -3.0], [0.0, 0.0, 1.0], (2.0, 4.0)),
        ([0.0, 0.0, -3.0], [-0.0, -0.0, 1.0], (2.0, 4.0)),
        ([0.0, 0.0, 3.0], [0.0, -0.0, -1.0], (2.0, 4.0)),
        ([-1.0, 0.0, -3.0], [0.0, 0.0, 1.0], (2.0, 4.0)),  # origin on the x = -1 plane, d.x = 0
        ([-1.0, 0.0, -3.0], [-0.0, 0.0, 1.0], (2.0, 4.0)),
        ([1.0, 1.0, -3.0], [0.0, 0.0, 1.0], (2.0, 4.0)),  # along an edge
        ([1.0, 1.0, -3.0], [-0.0, -0.0, 1.0], (2.0, 4.0)),
        ([1.0, 1.0, 1.0], [-0.0, -0.0, -1.0], (0.0, 2.0)),  # from a corner, along an edge
        ([1.0, 1.0, 1.0], [0.0, 0.0, 1.0], (-2.0, 0.0)),  # from a corner, outwards: touch at t=0
        ([1.0, 0.0, 0.0], [1.0, 0.0, 0.0], (-2.0, 0.0)),  # on a face, leaving
        ([1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], (0.0, 2.0)),  # on a face, entering
        ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0], (-1.0, 1.0)),  # sliding on a face
        ([1.0000001, 0.0, -3.0], [0.0, 0.0, 1.0], None),  # just outside, parallel
        ([2.0, 0.0, -3.0], [0.0, -0.0, 1.0], None),
        ([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], (-1.0, 1.0)),  # inside
    ]
    o = torch.tensor([r[0] for r in rows], dtype=dtype)
    d = torch.tensor([r[1] for r in rows], dtype=dtype)
    tn, tf = intersect_box(o, d, lo, hi)
    _no_nan(tn, tf)
    for k, (_, _, exp) in enumerate(rows):
        if exp is None:
            assert tn[k] > tf[k], f"row {k} should miss"
        else:
            assert (tn[k].item(), tf[k].item()) == pytest.approx(exp, abs=1e-6), f"row {k}"
    t0, t1, hit = clip_to_ray(tn, tf)
    _no_nan(t0, t1)
    assert hit.tolist() == [True] * 8 + [False, False, True, True, False, False, True]


@pytest.mark.parametrize("dtype", DTYPES)
def test_box_subnormal_and_overflowing_components(dtype):
    tiny = torch.finfo(dtype).tiny / 4  # subnormal: 1/tiny overflows
    o = torch.tensor([[-1.0, 0.0, -3.0], [-5.0, 0.0, -3.0], [0.0, 0.0, -3.0]], dtype=dtype)
    d = torch.tensor([[tiny, 0.0, 1.0], [tiny, 0.0, 1.0], [-tiny, tiny, 1.0]], dtype=dtype)
    tn, tf = intersect_box(o, d, [-1.0, -1.0, -1.0], [1.0, 1.0, 1.0])
    _no_nan(tn, tf)
    assert tn[0] <= tf[0] and tn[2] <= tf[2]
    assert tn[1] > tf[1]


@pytest.mark.parametrize("dtype", DTYPES)
def test_slab_parallel_rays(dtype):
    o = torch.tensor([[0.0, 0.5, 0.0], [0.0, -1.0, 0.0], [0.0, 2.0, 0.0], [0.0, 2.5, 0.0], [0.0, -3.0, 0.0]], dtype=dtype)
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, -0.0, 1.0], [0.6, 0.0, 0.8], [1.0, 0.0, 0.0], [1.0, -0.0, 0.0]], dtype=dtype)
    tn, tf = intersect_slab(o, d, -1.0, 2.0)
    _no_nan(tn, tf)
    assert tn[:3].tolist() == [-INF] * 3 and tf[:3].tolist() == [INF] * 3
    assert (tn[3:] > tf[3:]).all()
    t0, t1, hit = clip_to_ray(tn, tf, t_max=60.0)
    _no_nan(t0, t1)
    assert hit.tolist() == [True, True, True, False, False]
    assert t0[:3].tolist() == [0.0] * 3 and t1[:3].tolist() == [60.0] * 3
    # on a boundary plane, crossing it: touches at t = 0 then inside or outside
    o = torch.tensor([[0.0, 2.0, 0.0], [0.0, 2.0, 0.0]], dtype=dtype)
    d = torch.tensor([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]], dtype=dtype)
    tn, tf = intersect_slab(o, d, -1.0, 2.0)
    assert tn.tolist() == [-3.0, 0.0] and tf.tolist() == [0.0, 3.0]
    # per-ray layer bounds
    tn, tf = intersect_slab(o, d, torch.tensor([-1.0, 0.0], dtype=dtype), torch.tensor([2.0, 1.0], dtype=dtype))
    assert tn.tolist() == [-3.0, 1.0] and tf.tolist() == [0.0, 2.0]


@pytest.mark.parametrize("dtype", DTYPES)
def test_sphere_tangent_surface_and_inside(dtype):
    o = torch.tensor([[1.0, 0.0, -2.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.2, 0.1, 0.0],
                      [1.0, 0.0, 0.0]], dtype=dtype)
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, -0.0], [-1.0, 0.0, 0.0], [0.0, -0.0, 1.0], [0.0, 1.0, 0.0],
                      [1.0, 0.0, 0.0]], dtype=dtype)
    tn, tf = intersect_sphere(o, d, [0.0, 0.0, 0.0], 1.0)
    _no_nan(tn, tf)
    assert (tn[0].item(), tf[0].item()) == pytest.approx((2.0, 2.0), abs=1e-3)  # tangent
    assert (tn[1].item(), tf[1].item()) == (0.0, 0.0)  # on the surface, tangent: b = c = disc = 0
    assert (tn[2].item(), tf[2].item()) == pytest.approx((0.0, 2.0))
    assert (tn[3].item(), tf[3].item()) == pytest.approx((-1.0, 1.0))
    assert tn[4] < 0 < tf[4]
    assert (tn[5].item(), tf[5].item()) == pytest.approx((-2.0, 0.0))
    _, _, hit = clip_to_ray(tn, tf)
    assert hit.tolist() == [False, False, True, True, True, False]


def test_clip_to_ray_formula():
    tn = torch.tensor([-2.0, 1.0, 3.0, INF, -INF])
    tf = torch.tensor([5.0, 4.0, 2.0, -INF, INF])
    t0, t1, hit = clip_to_ray(tn, tf, t_max=3.5)
    assert t0.tolist() == [0.0, 1.0, 3.0, INF, 0.0]
    assert t1.tolist() == [3.5, 3.5, 2.0, -INF, 3.5]
    assert hit.tolist() == [True, True, False, False, True]
    t0, t1, hit = clip_to_ray(tn, tf, t_max=torch.tensor([1.0, 10.0, 10.0, 10.0, 10.0]))
    assert t1.tolist() == [1.0, 4.0, 2.0, -INF, 10.0] and hit.tolist() == [True, True, False, False, True]
    t0, t1, hit = clip_to_ray(tn, tf)
    assert t1.tolist() == tf.tolist()


# ---------------------------------------------------------------------------- property tests
BOX_LO = (-1.0, -0.5, -2.0)
BOX_HI = (1.0, 1.5, 0.25)
SPH_C = (0.25, -0.5, 0.5)
SPH_R = 1.5
SLAB = (-1.0, 2.0)
T_MAX = 20.0
N_SAMPLES = 2001  # spacing 0.01 over [0, T_MAX]


def _coord(special):
    """Coordinates that are often exactly on a plane of the bounds."""
    return st.one_of(st.sampled_from(special), st.floats(-4.0, 4.0, allow_nan=False, width=32))


def _dir_comp():
    return st.one_of(st.sampled_from([0.0, -0.0, 1.0, -1.0]), st.floats(-1.0, 1.0, allow_nan=False, width=32),
                     st.floats(-(2.0**-20), 2.0**-20, allow_nan=False, width=32))


def _rays(special):
    origin = st.tuples(*(_coord(special + (0.0,)) for _ in range(3)))
    direction = st.tuples(_dir_comp(), _dir_comp(), _dir_comp()).filter(lambda v: sum(x * x for x in v) > 1e-6)
    return st.lists(st.tuples(origin, direction), min_size=1, max_size=24)


def _tensors(rays, dtype):
    o = torch.tensor([r[0] for r in rays], dtype=torch.float64)
    d = torch.tensor([r[1] for r in rays], dtype=torch.float64)
    # normalise keeping exact zeros (and their sign) exact
    d = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)
    return o.to(dtype), d.to(dtype)


def _sdf_box(p):
    lo = torch.tensor(BOX_LO, dtype=p.dtype)
    hi = torch.tensor(BOX_HI, dtype=p.dtype)
    c, h = (lo + hi) / 2, (hi - lo) / 2
    q = (p - c).abs() - h
    return torch.linalg.vector_norm(q.clamp(min=0), dim=-1) + q.amax(-1).clamp(max=0)


def _sdf_sphere(p):
    return torch.linalg.vector_norm(p - torch.tensor(SPH_C, dtype=p.dtype), dim=-1) - SPH_R


def _sdf_slab(p):
    y = p[..., 1]
    return torch.maximum(SLAB[0] - y, y - SLAB[1])


def _check(o, d, tn, tf, sdf, dtype):
    """Never NaN; hit/miss agrees with dense sampling of the 1-Lipschitz SDF; ends on the surface."""
    _no_nan(tn, tf)
    t0, t1, hit = clip_to_ray(tn, tf, T_MAX)
    _no_nan(t0, t1)
    # dense reference in float64 along [0, T_MAX]
    ts = torch.linspace(0, T_MAX, N_SAMPLES, dtype=torch.float64)
    pts = o.double()[:, None, :] + ts[None, :, None] * d.double()[:, None, :]
    smin = sdf(pts).min(dim=1).values
    spacing = T_MAX / (N_SAMPLES - 1)
    margin = 1e-3
    surely_hit = smin < -margin  # a sample strictly inside
    surely_miss = smin > spacing / 2 + margin  # the SDF cannot dip below zero between samples
    assert (hit[surely_hit]).all(), f"missed rays that go inside: {o[surely_hit & ~hit]}, {d[surely_hit & ~hit]}"
    assert (~hit[surely_miss]).all(), f"hit rays that stay outside: {o[surely_miss & hit]}, {d[surely_miss & hit]}"
    # hits: ordered, and finite ends lie on the surface
    assert (tn[hit] <= tf[hit]).all()
    tol = 2e-4 if dtype == torch.float32 else 1e-9
    for t in (tn, tf):
        m = hit & torch.isfinite(t)
        p = o.double()[m] + t.double()[m, None] * d.double()[m]
        err = sdf(p).abs()
        bound = tol * (1 + t.double()[m].abs() + o.double()[m].abs().amax(-1))
        assert (err <= bound).all(), f"end point off the surface by {err.max() if err.numel() else 0}"
    # misses are canonical
    miss = tn > tf
    assert (tn[miss] == INF).all() and (tf[miss] == -INF).all()


SETTINGS = settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@pytest.mark.parametrize("dtype", DTYPES)
@SETTINGS
@given(rays=_rays(BOX_LO + BOX_HI))
def test_box_property(dtype, rays):
    o, d = _tensors(rays, dtype)
    tn, tf = intersect_box(o, d, torch.tensor(BOX_LO, dtype=dtype), torch.tensor(BOX_HI, dtype=dtype))
    _check(o, d, tn, tf, _sdf_box, dtype)
    # per-ray [R, 3] bounds give the same answer
    lo = torch.tensor(BOX_LO, dtype=dtype).expand_as(o)
    hi = torch.tensor(BOX_HI, dtype=dtype).expand_as(o)
    tn2, tf2 = intersect_box(o, d, lo, hi)
    assert torch.equal(tn, tn2) and torch.equal(tf, tf2)


@pytest.mark.parametrize("dtype", DTYPES)
@SETTINGS
@given(rays=_rays((SPH_C[0] + SPH_R, SPH_C[1] - SPH_R, SPH_C[2] + SPH_R, SPH_C[0], SPH_C[1], SPH_C[2])))
def test_sphere_property(dtype, rays):
    o, d = _tensors(rays, dtype)
    tn, tf = intersect_sphere(o, d, torch.tensor(SPH_C, dtype=dtype), SPH_R)
    _check(o, d, tn, tf, _sdf_sphere, dtype)


@pytest.mark.parametrize("dtype", DTYPES)
@SETTINGS
@given(rays=_rays(SLAB))
def test_slab_property(dtype, rays):
    o, d = _tensors(rays, dtype)
    tn, tf = intersect_slab(o, d, SLAB[0], SLAB[1])
    _check(o, d, tn, tf, _sdf_slab, dtype)
    parallel_inside = (d[:, 1] == 0) & (o[:, 1] >= SLAB[0]) & (o[:, 1] <= SLAB[1])
    assert (tn[parallel_inside] == -INF).all() and (tf[parallel_inside] == INF).all()


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**16), axis_parallel=st.booleans())
@pytest.mark.parametrize("kind, models", [
    ("box", [{"min": [-1, -2, -1], "max": [1.5, 2, 1]}, {"min": [-3, 0, -1], "max": [1, 1, 2]}]),
    ("slab", [{"y_min": -1.0, "y_max": 2.0}, {"y_min": 0.5, "y_max": 3.0}]),
    ("sphere", [{"center": [0, 1, 0], "radius": 2.0}, {"center": [1, 0, 0], "radius": 0.5}]),
    ("shell", [{"planet_radius": 6000.0, "bottom": 1.0, "top": 3.0}, {"planet_radius": 50.0, "bottom": 2.0, "top": 4.0}]),
])
def test_the_bounds_kernel_interval_is_the_eager_one(kind, models, seed, axis_parallel):
    """`bounds.intersect_kernel` (the kind's lanes interval traced by Dr.Jit, each ray's parameters
    gathered by scene) gives the eager interval: the same misses, a box's and a slab's ends bitwise,
    a sphere's and a shell's within 4 ulps (Dr.Jit's sqrt is correctly rounded, torch's float32 one
    not); origins inside and outside, rays along the axes."""
    from torchvol.geometry.bounds import BOUNDS, intersect_kernel
    from torchvol.runtime.compilation import drjit_available
    from torchvol.schema.batch import stack

    if not drjit_available():
        pytest.skip("Dr.Jit's LLVM backend is not available here")
    g = torch.Generator().manual_seed(seed)
    n = 400
    o = torch.randn(n, 3, generator=g) * 4
    d = torch.randn(n, 3, generator=g)
    if axis_parallel:  # every ray along one axis, either way
        d = torch.nn.functional.one_hot(torch.randint(0, 3, (n,), generator=g), 3).float() * torch.sign(d)
    d = torch.nn.functional.normalize(d, dim=1)
    s = torch.randint(0, 2, (n,), generator=g)
    k = BOUNDS[kind]
    b = stack([k.model(**m) for m in models], dtype=torch.float32, device=torch.device("cpu"))
    for got, want, end in zip(intersect_kernel(k, b, o, d, s), k.fn(b, o, d, s), ("near", "far")):
        fin = torch.isfinite(want)
        assert torch.equal(torch.isfinite(got), fin) and torch.equal(got[~fin], want[~fin]), f"{kind} {end}: another miss"
        err = (got - want)[fin].abs()
        ulps = 0 if kind in ("box", "slab") else 4
        allowed = ulps * torch.finfo(torch.float32).eps * want[fin].abs().clamp_min(1.0)
        worst = int((err - allowed).argmax()) if err.numel() else 0
        assert (err <= allowed).all(), f"{kind} {end}: error {err[worst]:.3g} at ray {worst} (allowed {allowed[worst]:.3g})"
