"""The precomputed transmittance-to-sun grid against exact and marched transmittance."""

import pytest
import torch
from conftest import assert_close

from torchvol.fields.grid import sample_grid
from torchvol.geometry.rays import intersect_box
from torchvol.volume.shadow import shadow_transmittance
from torchvol.volume.sun_volume import grid_layout, sun_frame, sun_transmittance_grid

F64 = torch.float64


@pytest.mark.parametrize("sun", [[0.0, 1.0, 0.0], [0.3, 0.8, -0.5], [1.0, 0.0, 0.0], [-0.2, -0.9, 0.4]])
def test_frame_is_orthonormal_and_w_is_the_sun(sun):
    frame = sun_frame(torch.tensor(sun, dtype=F64))
    assert torch.allclose(frame @ frame.T, torch.eye(3, dtype=F64), atol=1e-12)
    assert torch.allclose(frame[2], torch.nn.functional.normalize(torch.tensor(sun, dtype=F64), dim=0))
    assert torch.linalg.det(frame) > 0


@pytest.mark.parametrize("sun", [[0.0, 1.0, 0.0], [0.3, 0.8, -0.5], [0.9, 0.1, 0.2]])
def test_homogeneous_box_matches_beer_lambert_to_the_exit(sun):
    lo, hi, sigma = torch.tensor([-1.0, -0.5, -0.8], dtype=F64), torch.tensor([1.0, 0.5, 0.6], dtype=F64), 2.0
    inside = lambda p: ((p >= lo) & (p <= hi)).all(dim=1)  # noqa: E731
    ext = lambda p: sigma * inside(p).to(F64)  # noqa: E731
    grid = sun_transmittance_grid(ext, lo, hi, torch.tensor(sun, dtype=F64), resolution=96)
    g = torch.Generator().manual_seed(0)
    points = lo + (hi - lo) * torch.rand(500, 3, generator=g, dtype=F64) * 0.98 + 0.01 * (hi - lo)
    direction = torch.nn.functional.normalize(torch.tensor(sun, dtype=F64), dim=0).expand(500, 3)
    exact = torch.exp(-sigma * intersect_box(points, direction, lo, hi)[1])
    err = (grid.lookup(points, ext(points)) - exact).abs()
    # evaluating only the nodes inside the box (its chords) builds the same table
    evaluated = []
    counted = lambda p: evaluated.append(p.shape[0]) or ext(p)  # noqa: E731
    chorded = sun_transmittance_grid(counted, lo, hi, torch.tensor(sun, dtype=F64), resolution=96,
                                     chord=lambda o, d: intersect_box(o, d, lo, hi))
    assert_close(chorded.atlas, grid.atlas, atol=1e-12, what="optical depth and σ_t, chords vs every node")
    if sun != [0.0, 1.0, 0.0]:  # a tilted sun's table box reaches outside the box, and those nodes are skipped
        assert evaluated[0] < 0.8 * 96 * 96 * 97, f"{evaluated[0]} nodes evaluated: the chords saved nothing"
    # a hard face (density 0 → σ) smears over one cell of an oblique grid: worst near the faces.
    # Simpson's rule along the sun is a little worse on this step than the trapezoid rule (mean
    # 5.1e-3 against 4.4e-3) and better on smooth media (the parity cloud's image: 0.079% against 0.090%)
    assert err.max() < 4e-2, f"max error {err.max():.2e} at point {points[err.argmax()].tolist()}"
    assert err.mean() < 6e-3, f"mean error {err.mean():.2e}"


def test_grid_cloud_matches_a_fine_shadow_march():
    n = 32
    c = (torch.arange(n, dtype=F64) + 0.5) / n * 2 - 1
    z, y, x = torch.meshgrid(c, c, c, indexing="ij")
    density = (1.0 - (x**2 + y**2 + z**2).sqrt()).clamp_min(0) * (1.2 + 0.5 * torch.sin(5 * x) * torch.cos(4 * z))
    lo, hi = -torch.ones(3, dtype=F64), torch.ones(3, dtype=F64)
    sigma = 4.0
    ext = lambda p, owner=None: sigma * sample_grid(density, lo, hi, p)  # noqa: E731
    sun = torch.tensor([0.4, 0.8, -0.3], dtype=F64)
    grid = sun_transmittance_grid(ext, lo, hi, sun, resolution=96)
    g = torch.Generator().manual_seed(1)
    points = (torch.rand(400, 3, generator=g, dtype=F64) * 1.6 - 0.8)
    direction = torch.nn.functional.normalize(sun, dim=0).expand(400, 3)
    exit_t = intersect_box(points, direction, lo, hi)[1]
    marched = shadow_transmittance(points, direction, exit_t, ext, steps=512)
    err = (grid.lookup(points, ext(points)) - marched).abs()
    assert err.max() < 1e-2, f"max error {err.max():.2e} at {points[err.argmax()].tolist()}"


def test_render_with_a_shadow_grid_is_close_to_the_shadow_march_and_cheaper():
    import torchvol as tv
    from torchvol.measure.mitsuba import (
        puff_grid,
        relative_rmse,
        sigma_for,
        torchvol_scene,
    )

    grid = puff_grid(24)
    sigma = sigma_for(grid)
    march = torchvol_scene(grid, sigma, size=20, spp=1, shadow_steps=48)
    tabled = torchvol_scene(grid, sigma, size=20, spp=1, shadow_steps=48)
    tabled["lights"][0]["shadow"].update(method="grid", resolution=64)
    a, b = tv.render(march), tv.render(tabled)
    err = relative_rmse(b.radiance[0].numpy(), a.radiance[0].numpy())
    assert err < 0.01, f"shadow grid vs shadow march: relative RMSE {err:.3%}"
    assert b.stats["density_evals"] < a.stats["density_evals"]
    assert "volume0.shadow0" in b.stats["passes"]


def test_shadow_grid_refuses_slab_bounds():
    import torchvol as tv

    scene = {"lights": [{"shadow": {"method": "grid"}}], "volumes": [{"bounds": {"slab": {"y_min": 0, "y_max": 1}}}]}
    with pytest.raises(ValueError, match=r"lights\[0\]\.shadow\.method"):
        tv.load_scene(scene)


def test_shadow_grid_sees_only_the_medium_inside_sphere_bounds():
    """An fbm field is non-zero outside its sphere bounds (in the box's corners): the grid must not
    count that density, as the shadow march (which stops at the sphere) does not."""
    import torchvol as tv
    from torchvol.measure.mitsuba import relative_rmse

    scene = {"image": {"width": 20, "height": 16, "spp": 1}, "camera": {"eye": [0.0, 0.2, -3.0], "fov_y": 40},
             "lights": [{"direction": [0.6, 0.7, -0.4], "intensity": 5.0, "shadow": {"steps": 64}}],
             "volumes": [{"bounds": {"sphere": {"center": [0, 0, 0], "radius": 1.0}}, "sigma_t": 4.0,
                          "density": {"fbm": {"octaves": 2, "frequency": 1.5, "bias": 0.8}}}],
             "march": {"steps": 64}}
    march = tv.render(scene)
    scene["lights"][0]["shadow"].update(method="grid", resolution=192)
    grid = tv.render(scene)
    err = relative_rmse(grid.radiance[0].numpy(), march.radiance[0].numpy())
    # counting the corners gave 99%; what is left is the sphere's hard surface smeared over a grid
    # cell (1.9%, 0.69%, 0.30% at resolution 96, 192, 384)
    assert err < 0.01, f"shadow grid vs shadow march in a sphere: relative RMSE {err:.2%}"


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_the_lookup_is_grid_samples_bicubic(dtype):
    """The lookup is written in lanes (one source for eager and the Dr.Jit kernel); its bicubic
    interpolation is held to `F.grid_sample`'s, points past the table's box included."""
    lo, hi = torch.tensor([-1.0, -0.5, -0.8], dtype=dtype), torch.tensor([1.0, 0.5, 0.6], dtype=dtype)
    ext = lambda p: 1.0 + torch.sin(3.0 * p[:, 0]) * torch.cos(2.0 * p[:, 1] + p[:, 2])  # noqa: E731
    grid = sun_transmittance_grid(ext, lo, hi, torch.tensor([0.3, 0.8, -0.5], dtype=dtype), resolution=24)
    g = torch.Generator().manual_seed(1)
    points = (lo - 0.3 + (hi - lo + 0.6) * torch.rand(2000, 3, generator=g, dtype=F64).to(dtype))
    sigma = ext(points)
    m, n, pad = grid.to_atlas[0], grid.n, 2
    q = (grid.offset[0] + points[:, :1] * m[0] + points[:, 1:2] * m[1] + points[:, 2:3] * m[2])
    q = torch.minimum(q.clamp_min(0.0), q.new_tensor([n - 1.0, n - 1.0, grid.planes - 1.0]))
    plane = torch.ceil(q[:, 2])
    # the planes side by side, each with a replicated border (what the border rule reads past an edge)
    planes = grid.atlas.reshape(n, grid.planes, n, 2).permute(1, 3, 0, 2)  # (v, plane, u, channel) -> (plane, channel, v, u)
    atlas = torch.nn.functional.pad(planes, (pad,) * 4, mode="replicate").permute(1, 2, 0, 3).reshape(1, 2, n + 2 * pad, -1)
    x, y = q[:, 0] + pad + plane * (n + 2 * pad), q[:, 1] + pad
    coords = torch.stack([x / (atlas.shape[-1] - 1), y / (atlas.shape[-2] - 1)], dim=1).reshape(1, 1, -1, 2) * 2.0 - 1.0
    tau, feet = torch.nn.functional.grid_sample(atlas, coords, mode="bicubic", padding_mode="border",
                                                align_corners=True).reshape(2, -1)
    expected = torch.exp(-(tau.clamp_min(0.0) + 0.5 * (plane - q[:, 2]) * grid.plane_gap * (sigma + feet.clamp_min(0.0))))
    # float32: grid_sample's coordinates, normalised over the whole atlas, round the fraction
    # within a plane to ~1e-5 of a texel; the lookup's, within the plane, to ~1e-7
    assert_close(grid.lookup(points, sigma), expected, atol=1e-12 if dtype == F64 else 5e-6, what="lanes lookup vs grid_sample")


def test_the_kernel_builds_the_eager_tables():
    """`density_lanes.sun_grid_kernel` (the default) against `grid_atlas` (the reference) on a
    batch of two scenes with different suns: the same nodes evaluated, the tables within float
    rounding (the nodes' points are one fused multiply-add in both; τ is summed in float64 in both).
    The fog an fbm: its exponential profile would take its closed form, and no grid."""
    import torchvol as tv
    from torchvol.scene.presets import preset_dict
    from torchvol.volume.sun_volume import grid_atlas

    scenes = []
    for sun in ([0.3, 0.6, 0.75], [-0.5, 0.4, 0.2]):
        scene = preset_dict("multi-layer", width=24, height=16)
        scene["lights"][0].update(direction=sun, shadow={"method": "grid", "resolution": 40})
        scene["volumes"][1]["density"] = {"fbm": {"octaves": 2, "frequency": 0.5, "seed": 3}}
        scenes.append(scene)
    out = tv.render(scenes, keep_context=True)
    assert out.stats["plan"]["marches"] == {"volume0": "drjit", "volume1": "drjit"}
    for vol in out.context.volumes:
        grid = vol.sun_grids[0]
        lo, hi = vol.bounds.aabb(vol.params.bounds.value)
        eager, nodes = [], 0
        for b in range(2):
            owner = lambda q, b=b: torch.full((q.shape[0],), b, dtype=torch.long)  # noqa: E731
            layout = grid_layout(lo[b], hi[b], out.context.lights[0].direction[b], resolution=40,
                                 chord=lambda o, d, owner=owner: vol.intersect(o, d, owner(o)))
            eager.append(grid_atlas(lambda q, b=b, owner=owner: vol.params.sigma_t[b] * vol.field(q, owner(q)), layout))
            nodes += int(layout.count.sum())
        expected = torch.cat(eager)
        assert nodes > 0
        assert_close(grid.atlas, expected, atol=1e-5 * float(expected.abs().max()), what=f"{vol.plan.name}'s kernel-built sun grid")
