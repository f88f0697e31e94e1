"""The sphere-traced terrain: hits against the analytic plane, depth that unprojects onto the
heightfield, the cloud's shadow on the ground against a dense float64 march of the cloud's optical
depth towards the sun, finite output at odd sizes, the passes that ran, refusals."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import assert_close
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from kornia.geometry.depth import depth_to_3d_v2

import torchvol as tv
from torchvol import terrain as T
from torchvol.fields import DENSITIES
from torchvol.renderer.plan import make_plan
from torchvol.schema.batch import stack
from torchvol.terrain import Terrain


def _stacked(dtype=torch.float64, **terrain) -> object:
    return stack([Terrain(**terrain)], dtype=dtype)


def _world_points(out) -> torch.Tensor:
    """(B, H, W, 3) world points from depth, K and world_to_camera (kornia)."""
    cam = depth_to_3d_v2(out.depth.double()[:, 0], out.camera.K.double())
    c2w = torch.linalg.inv(out.camera.world_to_camera.double())
    return torch.einsum("bij,bhwj->bhwi", c2w[:, :3, :3], cam) + c2w[:, None, None, :3, 3]


def test_flat_terrain_hit_is_the_plane_intersection():
    g = torch.Generator().manual_seed(0)
    n, base = 400, 0.3
    o = torch.rand(n, 3, generator=g, dtype=torch.float64) * torch.tensor([8.0, 3.0, 8.0], dtype=torch.float64) - torch.tensor(
        [4.0, -0.5, 4.0], dtype=torch.float64)  # y in [0.5, 3.5]: above the plane
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    d[:, 1] = -d[:, 1].abs().clamp_min(0.2)  # downwards, as grazing as 1 in 5
    d = torch.nn.functional.normalize(d, dim=1)
    s = torch.zeros(n, dtype=torch.long)
    terrain = _stacked(base=base, amplitude=0.0, epsilon=1e-9, max_distance=1e4)
    hit, t = T.trace(terrain, o, d, s, torch.full((n,), math.inf, dtype=torch.float64), steps=2000)
    assert bool(hit.all())
    exact = (base - o[:, 1]) / d[:, 1]
    assert bool((t <= exact + 1e-12).all()), "the trace approaches from above"
    # the hit rule: vertical gap under epsilon·(1 + t), i.e. t within epsilon·(1 + t)/|d.y| of the plane's
    assert_close((exact - t) * d[:, 1].abs() / (1 + exact), 0.0, atol=1e-9, what="sphere-traced t vs the plane's")
    # rays that look up, or stop short of the plane, miss
    up, _ = T.trace(terrain, o, -d, s, torch.full((n,), math.inf, dtype=torch.float64), steps=50)
    short, _ = T.trace(terrain, o, d, s, 0.5 * (base - o[:, 1]) / d[:, 1], steps=2000)
    assert not up.any() and not short.any()


@pytest.mark.parametrize("hash_", ["table", "arithmetic"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_height_is_the_fbm_of_value_noise_of_each_scene(dtype, hash_):
    """The height is written once in lanes (eager and the Dr.Jit march's shadow rays); per scene it
    is `noise.fbm` of that scene's value noise in [−1, 1] (its table or arithmetic hash), to the bit."""
    from torchvol.noise import fast as fastnoise
    from torchvol.noise import lattice as noise

    value = {"table": noise.value_noise, "arithmetic": fastnoise.value_noise_hashed}[hash_]
    t = stack([Terrain(seed=3, base=0.2, amplitude=1.5, frequency=0.7, octaves=5, hash=hash_),
               Terrain(seed=11, base=-0.4, amplitude=0.8, frequency=1.3, octaves=5, hash=hash_)], dtype=dtype)
    g = torch.Generator().manual_seed(2)
    xz = (torch.rand(600, 2, generator=g, dtype=torch.float64) * 40.0 - 20.0).to(dtype)
    s = torch.arange(600) % 2
    for b, seed in enumerate((3, 11)):
        rows = s == b
        q = t.frequency[b] * torch.stack([xz[rows, 0], torch.zeros_like(xz[rows, 0]), xz[rows, 1]], dim=1)
        expected = t.base[b] + t.amplitude[b] * noise.fbm(q, lambda x: value(x, seed=seed) * 2.0 - 1.0, octaves=5)
        assert torch.equal(T.height(t, xz, s)[rows], expected), f"scene {b}"


def test_flat_terrain_normal_is_up():
    p = torch.tensor([[0.3, 0.0, -1.2], [5.0, 0.0, 7.0]], dtype=torch.float64)
    assert_close(T.normal(_stacked(amplitude=0.0), p, torch.zeros(2, dtype=torch.long)),
                 torch.tensor([[0.0, 1.0, 0.0]] * 2, dtype=torch.float64))


def test_normal_is_the_height_gradient():
    """Central differences against the gradient of the height by autograd."""
    terrain = _stacked(amplitude=1.2, frequency=0.4, seed=5, octaves=3)
    xz = (torch.rand(50, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 10 - 5).requires_grad_()
    s = torch.zeros(50, dtype=torch.long)
    h = T.height(terrain, xz, s)
    (grad,) = torch.autograd.grad(h.sum(), xz)
    p = torch.stack([xz[:, 0], h, xz[:, 1]], dim=1).detach()
    expected = torch.nn.functional.normalize(torch.stack([-grad[:, 0], torch.ones(50, dtype=torch.float64), -grad[:, 1]], 1), dim=1)
    assert_close(T.normal(terrain, p, s), expected, atol=5e-3, what="normal (central differences)")


def _hilly(width=17, height=13, **terrain):
    return {
        "image": {"width": width, "height": height},
        "camera": {"eye": [0.0, 3.0, -6.0], "target": [0.0, 0.0, 2.0], "fov_y": 50.0},
        "sky": {"kind": "constant", "radiance": [0.4, 0.5, 0.7]},
        "lights": [{"kind": "sun", "direction": [0.4, 0.8, 0.3], "intensity": 2.0, "shadow": {"steps": 4}}],
        "terrain": {"amplitude": 1.0, "frequency": 0.35, "seed": 2, "octaves": 4, "epsilon": 1e-5, "steps": 400, **terrain},
    }


def test_depth_unprojects_onto_the_terrain(one_thread):
    """kornia's depth_to_3d of the depth AOV, through the inverse world_to_camera, lands on the
    heightfield (within the hit rule's gap), and the normal AOV is the terrain's normal there."""
    out = tv.render(_hilly(), dtype=torch.float64)
    hit = out.depth[0, 0] > 0
    assert hit.float().mean() > 0.5 and not hit.all()  # terrain and sky both in view
    pts = _world_points(out)[0][hit]
    terrain = _stacked(**_hilly()["terrain"])
    s = torch.zeros(pts.shape[0], dtype=torch.long)
    gap = T.gap(terrain, pts, s)
    reach = (pts - torch.tensor(_hilly()["camera"]["eye"], dtype=torch.float64)).norm(dim=1)
    bound = 1e-5 * (1 + reach) + 1e-7 * reach  # the hit rule's gap, and the float32 depth's rounding
    assert bool((gap.abs() <= bound).all()), float((gap.abs() / bound).max())
    normal = out.aovs["normal"][0].permute(1, 2, 0)[hit].double()
    assert_close(normal, T.normal(terrain, pts, s), atol=1e-3, what="normal AOV")
    assert float(out.aovs["normal"][0].permute(1, 2, 0)[~hit].abs().max()) == 0.0


def _cloud_shadow_scene(**overrides):
    """terrain-clouds seen from below the cloud base (camera rays that hit the terrain never enter
    the cloud), no ambient: the terrain's radiance is albedo · n·l · E · T_cloud. A tight hit rule
    and no shadow offset: the shadow ray starts at the hit point itself."""
    scene = tv.load_scene("terrain-clouds", {
        "image.width": 24, "image.height": 24,
        "camera.eye": [0.0, 3.5, -6.0], "camera.target": [0.0, 0.0, 4.0],
        "terrain.ambient": [0.0, 0.0, 0.0], "lights.0.shadow.steps": 64,
        "terrain.epsilon": 1e-6, "terrain.shadow_offset": 0.0, **overrides})
    return scene.model_dump()


def test_cloud_darkening_follows_its_optical_depth_towards_the_sun(one_thread):
    """DESIGN item 6a: terrain under a cloud is darker than the same terrain with the cloud removed,
    and the darkening follows exp(−τ), τ the cloud's optical depth from the terrain point towards
    the sun, by a dense float64 march (4096 midpoints) of the cloud's density along the sun ray."""
    with_cloud = _cloud_shadow_scene()
    without = {**with_cloud, "volumes": []}
    lit = tv.render(with_cloud, dtype=torch.float64)
    bare = tv.render(without, dtype=torch.float64)
    ground = bare.depth[0, 0] > 0
    assert torch.equal(lit.depth[0, 0][ground], bare.depth[0, 0][ground]), "the same terrain"
    hit = ground & (bare.radiance[0, 1] > 1e-4)  # terrain that sees the sun
    ratio = (lit.radiance[0, 1] / bare.radiance[0, 1].clamp_min(1e-12))[hit].double()

    points = _world_points(bare)[0][hit]
    scene = tv.load_scene(with_cloud)
    sun = torch.nn.functional.normalize(torch.tensor(scene.lights[0].direction, dtype=torch.float64), dim=0)
    vol = scene.volumes[0]
    y0, y1 = vol.bounds.slab.y_min, vol.bounds.slab.y_max
    field = DENSITIES["fbm"].fn(stack([vol], dtype=torch.float64).density.value, torch.zeros(1, dtype=torch.float64))
    k = 4096
    t_in, t_out = (y0 - points[:, 1]) / sun[1], (y1 - points[:, 1]) / sun[1]
    u = (torch.arange(k, dtype=torch.float64) + 0.5) / k
    t = t_in[:, None] + (t_out - t_in)[:, None] * u[None, :]
    q = points[:, None, :] + t[..., None] * sun
    density = field(q.reshape(-1, 3), torch.zeros(q.shape[0] * k, dtype=torch.long)).view(-1, k)
    tau = vol.sigma_t * density.sum(dim=1) * (t_out - t_in) / k
    expected = torch.exp(-tau)

    assert (expected < 0.5).any() and (expected > 0.95).any(), "the view must hold shadowed and open ground"
    assert bool((ratio <= 1.0 + 1e-12).all()), "a cloud never brightens the terrain"
    # measured: max 1.4e-4, mean 1.4e-5 (64 shadow steps against 4096)
    assert_close(ratio, expected, atol=1e-3, what="darkening vs exp(-tau)")
    assert float((ratio - expected).abs().mean()) < 1e-4


@pytest.mark.parametrize("width,height", [(7, 5), (5, 9), (11, 3)])
def test_finite_at_odd_sizes_and_in_a_batch(width, height, one_thread):
    scenes = [tv.load_scene("terrain-clouds", {"image.width": width, "image.height": height, "march.steps": 6,
                                               "terrain.seed": seed}) for seed in (1, 2)]
    out = tv.render(scenes)
    assert out.image.shape == (2, 3, height, width)
    for x in (out.image, out.radiance, out.depth, out.alpha, *out.aovs.values()):
        assert bool(torch.isfinite(x).all())
    assert (out.depth > 0).any()
    alone = tv.render(scenes[1])
    assert torch.equal(alone.radiance[0], out.radiance[1]) and torch.equal(alone.depth[0], out.depth[1])


def test_passes_are_those_that_ran(one_thread):
    scene = tv.load_scene(_hilly(9, 7))
    out = tv.render(scene)
    assert make_plan(scene).names() == out.stats["plan"]["passes"] == out.stats["passes"]
    assert out.stats["passes"][:5] == ["rays", "sky", "terrain.trace", "terrain.shade", "terrain.shadow0"]
    plain = tv.render({**_hilly(9, 7), "lights": [{"kind": "sun", "direction": [0.4, 0.8, 0.3]}]}).stats["passes"]
    assert not any("shadow" in p for p in plain), plain
    assert not any("terrain" in p for p in make_plan(tv.preset("cloud-puff")).names())


def test_terrain_and_voxels_load_together():
    """No longer refused: both surfaces render as one (tests/test_surfaces_together.py)."""
    scene = tv.preset("voxel-terrain", width=8, height=8).model_dump()
    scene["terrain"] = {}
    assert tv.load_scene(scene).terrain is not None


def test_bad_terrain_values_name_the_key():
    with pytest.raises(ValueError, match=r"terrain\.safety"):
        tv.load_scene({"terrain": {"safety": 0.0}})
    with pytest.raises(ValueError, match=r"terrain\.amplitude"):
        tv.load_scene({"terrain": {"amplitude": -1.0}})


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(o=st.lists(st.floats(-5, 5), min_size=3, max_size=3), d=st.lists(st.floats(-1, 1), min_size=3, max_size=3),
       amplitude=st.floats(0.0, 3.0), safety=st.floats(0.05, 1.0))
def test_trace_is_finite_for_any_ray(o, d, amplitude, safety):
    """Origins under or on the terrain, horizontal and zero-component directions: finite t, no NaN."""
    d = torch.tensor([d], dtype=torch.float32)
    if float(d.norm()) < 1e-3:
        d = torch.tensor([[0.0, 0.0, 1.0]])
    d = torch.nn.functional.normalize(d, dim=1)
    terrain = _stacked(torch.float32, amplitude=amplitude, safety=safety)
    o = torch.tensor([o], dtype=torch.float32)
    hit, t = T.trace(terrain, o, d, torch.zeros(1, dtype=torch.long), torch.full((1,), math.inf), steps=64)
    assert bool(torch.isfinite(t).all())
    vis = T.visibility(terrain, o, d, torch.zeros(1, dtype=torch.long), torch.full((1,), math.inf), steps=64)
    assert vis.item() in (0.0, 1.0)


def test_no_shadow_acne_under_a_high_sun(one_thread):
    """Hits are refined onto the surface: the shadow ray must still start clear of the hit rule's
    width at that distance, or distant slopes shadow themselves in isolated pixels."""
    scene = {
        "image": {"width": 48, "height": 32},
        "camera": {"eye": [0.0, 6.0, -14.0], "target": [0.0, 0.0, 10.0], "fov_y": 55.0},
        "lights": [{"kind": "sun", "direction": [0.1, 1.0, 0.05], "intensity": 1.0, "shadow": {"steps": 4}}],
        "terrain": {"amplitude": 1.5, "frequency": 0.15, "octaves": 6, "ambient": [0.0] * 3, "max_distance": 80.0},
    }
    lit = tv.render(scene)
    bare = tv.render({**scene, "lights": [{**scene["lights"][0], "shadow": None}]})
    hit = lit.depth[0, 0] > 0
    shadowed = (lit.radiance[0, 1] < 0.5 * bare.radiance[0, 1]) & hit
    assert float(shadowed.sum()) / float(hit.sum()) < 0.01, f"{int(shadowed.sum())} of {int(hit.sum())} hits self-shadowed"


@pytest.mark.parametrize("hash_", ["table", "arithmetic"])
def test_the_kernel_trace_is_bitwise_the_eager_trace(hash_):
    """`trace_kernel` (Dr.Jit's loop of the same `trace_step` and `onto_surface`): the same hits and
    distances, bitwise, over rays from above, below and inside the terrain's slab, grazing ones too."""
    from torchvol.runtime.compilation import drjit_available

    if not drjit_available():
        pytest.skip("Dr.Jit's LLVM backend is not available")
    t = stack([Terrain(seed=3, amplitude=2.0, frequency=0.4, hash=hash_), Terrain(seed=5, amplitude=1.0, safety=0.8, hash=hash_)],
              dtype=torch.float32)
    g = torch.Generator().manual_seed(0)
    n = 3000
    o = torch.rand(n, 3, generator=g) * torch.tensor([20.0, 6.0, 20.0]) - torch.tensor([10.0, 2.0, 10.0])
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=1)
    d[: n // 10, 1] = 1e-3  # grazing
    d = torch.nn.functional.normalize(d, dim=1)
    s = torch.arange(n) % 2
    hit, dist = T.trace(t, o, d, s, torch.full((n,), math.inf), steps=128, refine=True)
    k_hit, k_dist = T.trace_kernel(t, o, d, s)
    assert hit.any() and (~hit).any()
    assert torch.equal(hit, k_hit), f"{int((hit != k_hit).sum())} hits differ"
    assert torch.equal(dist, k_dist), f"{int((dist != k_dist).sum())} distances differ, by up to {float((dist - k_dist).abs().max()):.3g}"


def test_the_kernel_normal_is_the_eager_normal():
    """`normal_kernel` (Dr.Jit, the same `normal_lanes`) against `normal` on torch, float32, over
    two scenes' hills: the same float32 arithmetic, apart from the order of a few roundings."""
    from torchvol.runtime.compilation import drjit_available

    if not drjit_available():
        pytest.skip("Dr.Jit's LLVM backend is not available")
    t = stack([Terrain(seed=3, amplitude=2.0, frequency=0.4), Terrain(seed=5, amplitude=1.0, octaves=6)], dtype=torch.float32)
    g = torch.Generator().manual_seed(1)
    p = torch.rand(2000, 3, generator=g) * 20.0 - 10.0
    s = torch.arange(2000) % 2
    eager, kernel = T.normal(t, p, s), T.normal_kernel(t, p, s)
    assert float(eager[:, 1].min()) < 0.9  # slopes, not a flat test
    assert_close(kernel, eager, atol=1e-5, what="kernel normal")


def test_the_shading_kernel_is_the_shading_of_its_parts(monkeypatch):
    """The terrain's shading as one kernel (normal, look, the sky's and the sun's rays through a
    cloud and the terrain, `_colour`) against the same passes each its own kernel
    (`surface_shadows`): the same image and depth bitwise, the same passes listed, the same
    density evaluations; two scenes of different suns in a batch, one low (many slopes face away
    from it: their shadow rays, which would cross the cloud, are not traced)."""
    from torchvol.runtime.compilation import drjit_available
    from torchvol.volume import kernel_march

    if not drjit_available():
        pytest.skip("Dr.Jit's LLVM backend is not available")
    scenes = []
    for sun in ([0.35, 1.0, 0.45], [1.0, 0.2, 0.3]):
        scene = tv.preset("terrain-clouds", width=40, height=28).model_dump()
        scene["lights"][0]["direction"] = sun
        scenes.append(scene)
    fused = tv.render(scenes, seed=1)
    monkeypatch.setattr(kernel_march, "surface_lanes_of", lambda ctx, uses, s: None)
    parts = tv.render(scenes, seed=1)
    assert torch.equal(fused.radiance, parts.radiance), f"largest difference {float((fused.radiance - parts.radiance).abs().max()):.3g}"
    assert torch.equal(fused.depth, parts.depth)
    assert list(fused.stats["time_s"]) == list(parts.stats["time_s"])
    assert fused.stats["density_evals"] == parts.stats["density_evals"]
