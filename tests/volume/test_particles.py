"""The particles density (fields/particles.py): K moving spheres, each with its own noise, in one
medium. A particle without noise is a sphere of known density and optical depth; motion moves each
particle's whole density by v·t; draws depend on the seed alone."""

import math

import pytest
import torch
from conftest import assert_close
from hypothesis import given, settings
from hypothesis import strategies as st

import torchvol as tv
from torchvol.fields.particles import (
    ParticleField,
    falloff,
    particle_cells,
    particle_draws,
)
from torchvol.schema.batch import stack

F64 = torch.float64


def field(time: float = 0.0, **density) -> ParticleField:
    scene = tv.load_scene({"time": time, "volumes": [{"bounds": {"box": {"min": [-2, -2, -2], "max": [2, 2, 2]}},
                                                      "density": {"particles": density}}]})
    batch = stack([scene], dtype=F64)
    return ParticleField(batch.volumes[0].density.value, batch.time)


def sphere(core=0.7, r=0.5, edge=0.4, center=(0.1, -0.2, 0.3)) -> dict:
    return {"count": 1, "region_min": center, "region_max": center, "radius": (r, r), "amplitude": 0.0, "core": core,
            "edge": edge}


def test_a_particle_without_noise_is_a_sphere_of_known_density(one_thread):
    f = field(**sphere())
    c = torch.tensor([0.1, -0.2, 0.3], dtype=F64)
    d = torch.randn(200, 3, dtype=F64)
    d = d / d.norm(dim=1, keepdim=True)
    s = torch.linspace(0.0, 1.3, 200, dtype=F64)  # in radii
    got = f(c + 0.5 * s[:, None] * d, torch.zeros(200, dtype=torch.long))
    t = ((s - 0.6) / 0.4).clamp(0, 1)
    assert_close(got, 0.7 * (1 - t * t * (3 - 2 * t)), what="sphere density")
    assert (got[s >= 1.0] == 0).all() and (got[s <= 0.6] == 0.7).all()


def test_the_optical_depth_through_a_sphere_is_analytic(one_thread):
    # through the centre: τ = σ_t · 2 r core (1 − edge/2) (the falloff is symmetric about its middle)
    core, r, edge, sigma = 0.8, 0.6, 0.5, 2.0
    scene = {"image": {"width": 9, "height": 9}, "camera": {"eye": [0, 0, -3], "target": [0, 0, 0], "fov_y": 20.0},
             "volumes": [{"bounds": {"box": {"min": [-1, -1, -1], "max": [1, 1, 1]}},
                          "density": {"particles": sphere(core, r, edge, (0.0, 0.0, 0.0))}, "sigma_t": sigma}],
             "march": {"steps": 400, "dither": "none"}}
    out = tv.render(scene, dtype=F64)
    tau = sigma * 2 * r * core * (1 - edge / 2)
    assert_close(out.alpha[0, 0, 4, 4], torch.tensor(1 - math.exp(-tau), dtype=F64), atol=2e-4, what="alpha")
    assert out.stats["passes"] == ["rays", "volume0.march", "composite"]


def test_motion_moves_each_particle_by_velocity_times_time(one_thread):
    params = {"count": 5, "seed": 4, "speed": 0.7, "wind": (0.2, -0.1, 0.05), "radius": (0.2, 0.3)}
    f0, f1 = field(0.0, **params), field(1.5, **params)
    v = torch.tensor([0.2, -0.1, 0.05], dtype=F64) + 0.7 * particle_draws(4, 5)["direction"]
    assert_close(f1.centers[0] - f0.centers[0], 1.5 * v, atol=1e-12, what="displacement")
    # a particle's whole density (noise included) travels with it
    one = dict(params, count=1)
    v1 = torch.tensor([0.2, -0.1, 0.05], dtype=F64) + 0.7 * particle_draws(4, 1)["direction"][0]
    pts = field(0.0, **one).centers[0, 0] + 0.5 * torch.rand(100, 3, dtype=F64, generator=torch.Generator().manual_seed(0)) - 0.25
    s = torch.zeros(100, dtype=torch.long)
    moved, still = field(1.5, **one)(pts + 1.5 * v1, s), field(0.0, **one)(pts, s)
    assert_close(moved, still, atol=1e-9, what="moved density")
    assert (still > 0).sum() > 20


def test_draws_depend_on_the_seed_alone(one_thread):
    a, b = particle_draws(11, 8), particle_draws(11, 8)
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not torch.equal(a["position"], particle_draws(12, 8)["position"])
    pts = torch.rand(500, 3, dtype=F64, generator=torch.Generator().manual_seed(1)) * 2 - 1
    s = torch.zeros(500, dtype=torch.long)
    assert torch.equal(field(seed=11)(pts, s), field(seed=11)(pts, s))
    assert not torch.equal(field(seed=11)(pts, s), field(seed=12)(pts, s))


def test_a_batch_of_seeds_evaluates_as_each_alone(one_thread):
    scenes = [tv.load_scene({"volumes": [{"bounds": {"box": {"min": [-2, -2, -2], "max": [2, 2, 2]}},
                                          "density": {"particles": {"seed": seed, "count": 6}}}]}) for seed in (1, 2)]
    both = stack(scenes, dtype=F64)
    fb = ParticleField(both.volumes[0].density.value, both.time)
    pts = torch.rand(400, 3, dtype=F64, generator=torch.Generator().manual_seed(2)) * 2 - 1
    s = torch.arange(400) % 2
    got = fb(pts, s)
    for b in (0, 1):
        assert torch.equal(got[s == b], field(seed=b + 1, count=6)(pts[s == b], torch.zeros(200, dtype=torch.long)))


def test_sum_and_max_and_the_bound(one_thread):
    pts = torch.rand(3000, 3, dtype=F64, generator=torch.Generator().manual_seed(3)) * 4 - 2
    s = torch.zeros(3000, dtype=torch.long)
    total, top = field(seed=5, count=12)(pts, s), field(seed=5, count=12, combine="max")(pts, s)
    assert (top <= total + 1e-12).all() and (total > top).any()
    lo, hi = field(seed=5, count=12).aabb()
    inside = ((pts >= lo[0]) & (pts <= hi[0])).all(dim=1)
    assert (total[~inside] == 0).all() and (total[inside] > 0).any()


@settings(max_examples=25, deadline=None)
@given(scale=st.sampled_from([0.0, 1e-8, 1.0, 1e4]), edge=st.floats(0.01, 1.0), lod=st.integers(0, 3))
def test_finite_and_signed_agrees_with_density(scale, edge, lod):
    f = field(seed=9, count=7, edge=edge, octaves=4)
    pts = torch.cat([f.centers[0], f.centers[0] + f.radii[0, :, None] * torch.tensor([1.0, 0, 0], dtype=F64),
                     scale * torch.randn(50, 3, dtype=F64, generator=torch.Generator().manual_seed(4))])
    s = torch.zeros(len(pts), dtype=torch.long)
    lods = torch.full((len(pts),), lod)
    d, g = f(pts, s, lods), f.signed(pts, s, lods)
    assert torch.isfinite(d).all() and torch.isfinite(g).all() and (d >= 0).all()
    assert torch.equal(g.clamp_min(0.0), d)
    far = (pts[:, None] - f.centers[0][None]).norm(dim=2).div(f.radii[0]).amin(dim=1) > 1.0
    assert (g[far] < 0).all()


def test_falloff_is_smooth_and_bounded():
    r = torch.linspace(0, 2, 101, dtype=F64)
    w = falloff(r, torch.tensor(0.3, dtype=F64))
    assert (w[r <= 0.7] == 1).all() and (w[r >= 1] == 0).all() and (w.diff() <= 0).all()


@pytest.mark.parametrize("key, value", [("radius", [0.5, 0.2]), ("region_max", [-2.0, 0.0, 0.0]), ("count", 0),
                                        ("edge", 0.0)])
def test_bad_values_are_refused_naming_the_key(key, value):
    with pytest.raises(ValueError, match=key):
        field(**{key: value})


@pytest.mark.slow  # ~6 s of CPU (a 512-step reference)
def test_error_controlled_marching_converges_on_particles(one_thread):
    # the tolerance march reads signed() between samples; it must agree with a fine fixed march
    scene = {"image": {"width": 8, "height": 8}, "camera": {"eye": [0, 0.3, -3.5], "target": [0, 0, 0], "fov_y": 45.0},
             "lights": [{"kind": "sun", "direction": [0.5, 0.8, -0.4], "intensity": 3.0, "shadow": {"steps": 8}}],
             "volumes": [{"bounds": {"box": {"min": [-1.8, -1.5, -1.5], "max": [1.8, 1.5, 1.5]}},
                          "density": {"particles": {"count": 10, "seed": 2, "core": -0.3, "amplitude": 2.5, "frequency": 3.0}},
                          "sigma_t": 6.0, "albedo": 0.9}]}
    fine = tv.render({**scene, "march": {"steps": 512, "dither": "none"}})
    tol = tv.render({**scene, "march": {"tolerance": 0.01}})
    assert "volume0.march" in tol.stats["passes"]
    assert_close(tol.radiance, fine.radiance, atol=0.01, what="tolerance march vs 512 steps")


@settings(max_examples=30, deadline=None)
@given(count=st.integers(1, 40), seed=st.integers(0, 10_000), spread=st.sampled_from([1e-3, 0.3, 1.0, 50.0]),
       cells=st.integers(1, 9), far=st.sampled_from([0.0, 3e4, -1e6]))
def test_a_cell_lists_every_particle_that_holds_a_point_in_it(count, seed, spread, cells, far):
    """`particle_cells`: a point, put in a cell by the kernel's float32 lookup, finds in that cell's
    list every particle whose sphere holds it by the kernel's float32 test (|p − c| / r < 1), the
    lists ascending. Points: each cell's nearest to each centre (where a sphere barely reaches a
    cell), on the cells' faces, spread over the box and beyond it; boxes near and far from the origin."""
    g = torch.Generator().manual_seed(seed)
    centers = (far + spread * torch.randn(2, count, 3, generator=g)).float()  # far: float32 rounds coarsely
    radii = (spread * (0.05 + torch.rand(2, count, generator=g))).float()
    low, per_unit, first, rows = particle_cells(centers, radii, cells=cells)
    size = 1.0 / per_unit  # (2, 3)
    grid = torch.stack(torch.meshgrid(*[torch.arange(cells, dtype=torch.float64)] * 3, indexing="ij")[::-1], -1)
    corner = low[:, None] + grid.reshape(1, -1, 3) * size[:, None]  # (2, C, 3)
    nearest = torch.minimum(torch.maximum(centers.double()[:, None], corner[:, :, None]), (corner + size[:, None])[:, :, None])
    b = torch.arange(2)[:, None].expand(-1, nearest.shape[1] * count).reshape(-1)
    n = 3000
    bn = torch.randint(0, 2, (n,), generator=g)
    faces = low[bn] + size[bn] * torch.randint(0, cells + 1, (n, 3), generator=g)
    spread_out = low[bn] + size[bn] * cells * (1.2 * torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.1)
    p = torch.cat([nearest.reshape(-1, 3), faces, spread_out]).float()
    b = torch.cat([b, bn, bn])
    cell = ((p - low[b].float()) * per_unit[b].float()).clamp(0.0, cells - 1.0).floor().long()
    at = b * cells**3 + (cell[:, 2] * cells + cell[:, 1]) * cells + cell[:, 0]
    listed = torch.zeros(2 * cells**3, count, dtype=torch.bool)  # cell -> its particles
    owner = torch.repeat_interleave(torch.arange(2 * cells**3), first.diff())
    listed[owner, rows % count] = True
    assert torch.equal(rows // count, owner // cells**3)  # a scene's cells list its own particles
    assert all(bool((rows[first[c]:first[c + 1]].diff() > 0).all()) for c in range(2 * cells**3))
    holds = ((p[:, None] - centers[b]).norm(dim=-1) / radii[b]) < 1.0  # [N, K]
    missing = holds & ~listed[at]
    worst = int(missing.any(dim=1).float().argmax())
    assert not bool(missing.any()), (f"{int(missing.any(dim=1).sum())} points miss a particle that holds them, e.g. "
                                     f"{p[worst].tolist()} of scene {int(b[worst])} in cell {int(at[worst])}: "
                                     f"particles {missing[worst].nonzero().flatten().tolist()}")
