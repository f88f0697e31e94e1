"""Path tracing of physical media (`[path]`, torchvol/volume/path.py).

Analytic oracles: the volume furnace (a camera deep inside a homogeneous, isotropic, emissive
medium sees (e/σ_t)·Σ_{k=0..B} a^k with B bounces); `bounces = 1` is the single-scattering
integral the march computes (a sun through a heterogeneous grid cloud; a point light inside a
homogeneous box). Noise is estimated from independent renders (a batch of scenes with different
seeds), never assumed."""

from __future__ import annotations

import copy
import math

import pytest
import torch
from conftest import assert_close
from hypothesis import given, settings
from hypothesis import strategies as st

import torchvol as tv
from torchvol.measure.mitsuba import puff_grid, sigma_for, torchvol_scene
from torchvol.renderer.executor import camera_for
from torchvol.schema.validate import SceneError
from torchvol.volume.path import hg_cos

F64 = torch.float64


def _furnace(albedo: float, bounces: int, *, sigma: float = 2.0, e: float = 0.7, samples: int = 32) -> dict:
    return {"image": {"width": 4, "height": 4}, "camera": {"eye": [0, 0, 0], "target": [0, 0, 1], "fov_y": 40},
            "volumes": [{"bounds": {"sphere": {"center": [0, 0, 0], "radius": 400.0}}, "density": {"constant": 1.0},
                         "sigma_t": sigma, "albedo": albedo, "emission": [e, e, e]}],
            "path": {"bounces": bounces, "samples": samples}}


def _mean_and_error(values: torch.Tensor) -> tuple[float, float]:
    """The mean of independent estimates and its standard error."""
    values = values.double().reshape(-1)
    return float(values.mean()), float(values.std() / math.sqrt(values.numel()))


@pytest.mark.parametrize(("albedo", "bounces"), [(0.0, 4), (0.5, 3), (0.9, 12), (1.0, 6),
                                               pytest.param(0.99, 256, marks=pytest.mark.slow)])
def test_the_volume_furnace(albedo, bounces, one_thread):
    """Every pixel is an independent estimate of (e/σ_t)·Σ_{k=0..B} a^k: the image's mean is within
    five standard errors (estimated from the pixels) of it; exact where no path is random."""
    sigma, e = 2.0, 0.7
    out = tv.render(_furnace(albedo, bounces, sigma=sigma, e=e), dtype=F64)
    expected = e / sigma * sum(albedo**k for k in range(bounces + 1))
    mean, error = _mean_and_error(out.radiance)
    assert abs(mean - expected) <= 5.0 * error + 1e-6 * expected, (
        f"furnace a={albedo} B={bounces}: {mean:.6g} against {expected:.6g} (standard error {error:.3g})")


def _single_scattering_check(scene: dict, samples: int, seeds: int = 4, dtype: torch.dtype = F64) -> None:
    """`bounces = 1` against the march (fine steps, float64 unless `dtype`): the means of `seeds`
    independent path-traced images (a batch of the scene with different seeds) within five
    standard errors."""
    march = tv.render(scene, dtype=dtype)
    traced = tv.render([{**scene, "path": {"bounces": 1, "samples": samples}}] * seeds, seed=list(range(seeds)), dtype=dtype)
    means = traced.radiance.double().mean(dim=(1, 2, 3))
    mean, error = _mean_and_error(means)
    expected = float(march.radiance.double().mean())
    assert abs(mean - expected) <= 5.0 * error, f"single scattering: path {mean:.6g} ± {error:.2g}, march {expected:.6g}"
    assert error < 0.05 * expected  # the check is sharp enough to fail


def test_one_bounce_is_the_marched_single_scattering_of_a_sun_through_a_cloud(one_thread):
    grid = puff_grid(12)
    scene = torchvol_scene(grid, sigma_for(grid, 4.0), size=6, spp=1, shadow_steps=64)
    scene["march"] = {"quality": "high", "steps": 192}
    _single_scattering_check(scene, samples=48)


def test_one_bounce_is_the_marched_single_scattering_of_a_point_light(one_thread):
    scene = {"image": {"width": 6, "height": 6}, "camera": {"eye": [0, 0.2, -3], "target": [0, 0, 0], "fov_y": 35},
             "lights": [{"kind": "point", "position": [0.3, 1.8, -0.2], "intensity": 6.0, "shadow": {"steps": 64}}],
             "volumes": [{"bounds": {"box": {"min": [-1, -1, -1], "max": [1, 1, 1]}}, "density": {"constant": 1.0},
                          "sigma_t": 1.5, "albedo": 0.8, "phase": {"hg": {"g": 0.4}}}],
             "march": {"quality": "high", "steps": 192, "closed_form": False}}
    _single_scattering_check(scene, samples=48)


@pytest.mark.parametrize("lit", [False, True])
def test_one_bounce_blends_into_the_sky_as_the_march_does(lit, one_thread):
    """A volume's `sky_blend` (the source at distance t mixed into σt·sky by 1 − e^{−k t²}) on the
    paths: a collision on the camera ray gathers (1 − w) of its light and adds w·sky behind the
    ray; w from ~0.3 to ~0.9 across the box, under a gradient sky. Unlit, an emitting absorber:
    one bounce is the march. Lit by a sun and a point light: the light they add to one bounce (the
    paths' sky scattered once, which the march leaves out, cancels) is the march's."""
    scene = {"image": {"width": 6, "height": 6}, "camera": {"eye": [0, 0.2, -3], "target": [0, 0, 0], "fov_y": 35},
             "sky": {"kind": "gradient", "horizon": [0.9, 0.6, 0.3], "slope": [-0.5, 0.0, 0.6]},
             "lights": [{"direction": [0.4, 1.0, -0.3], "intensity": 0.0}],
             "volumes": [{"bounds": {"box": {"min": [-1, -1, -1], "max": [1, 1, 1]}}, "density": {"constant": 1.0},
                          "sigma_t": 1.5, "albedo": 0.0, "emission": [0.6, 0.3, 0.1], "sky_blend": 0.12}],
             "march": {"quality": "high", "steps": 192, "closed_form": False}}
    if not lit:
        _single_scattering_check(scene, samples=48)
        unblended = tv.render({**scene, "volumes": [{**scene["volumes"][0], "sky_blend": None}]}, dtype=F64)
        assert float((tv.render(scene, dtype=F64).radiance - unblended.radiance).abs().mean()) > 0.05  # the blend shows
        return
    scene["volumes"][0].update(albedo=0.8, phase={"hg": {"g": 0.4}})
    lit_scene = {**scene, "lights": [{"direction": [0.4, 1.0, -0.3], "intensity": 2.0, "shadow": {"steps": 64}},
                                     {"kind": "point", "position": [0.3, 1.8, -0.2], "intensity": 6.0, "shadow": {"steps": 64}}]}
    seeds, added = 4, {}
    for name, sc in (("march", None), ("paths", {"bounces": 1, "samples": 32})):
        a, b = ([{**x, "path": sc}] * seeds for x in (lit_scene, scene))
        added[name] = (tv.render(a, seed=list(range(seeds)), dtype=F64).radiance - tv.render(b, seed=list(range(seeds)), dtype=F64).radiance).mean(dim=(1, 2, 3))
    mean, error = _mean_and_error(added["paths"])
    expected = float(added["march"].mean())
    assert abs(mean - expected) <= 5.0 * error and error < 0.05 * expected, f"the lights' light: path {mean:.6g} ± {error:.2g}, march {expected:.6g}"


def test_a_point_lights_furnace(one_thread):
    """A point light of intensity I at the centre of a sphere that scatters and never absorbs
    (albedo 1): all its power leaves the sphere, symmetrically about the light, and the part that
    scattered, 1 − e^{−τ} (τ the optical depth from the centre out; the rest is the light itself, a
    point no pixel sees),
    gives a camera at distance D the irradiance (1 − e^{−τ})·I/D² whatever the phase function
    and the orders: Σ L·cos θ·dΩ over the image (cos⁴θ/f² a pixel). Each seed's image is an
    independent estimate; their mean within five standard errors. The light's 1/r² peak inside
    the medium is what a collision's next event cannot average (7% off over four seeds)."""
    distance, size, fov, seeds = 4.0, 24, 34.0, 12
    # σ_t·(1 − r) (fbm with no noise): τ from the centre = σ_t/2, the limb fades out, so the pixels'
    # jittered sub-samples there add no noise of their own
    cone = {"fbm": {"amplitude": 0.0, "bias": 1.0, "radial": 1.0, "octaves": 1}}
    scene = {"image": {"width": size, "height": size, "spp": 4},
             "camera": {"eye": [0, 0, -distance], "target": [0, 0, 0], "fov_y": fov},
             "lights": [{"kind": "point", "position": [0, 0, 0], "intensity": 1.0}],
             "volumes": [{"bounds": {"sphere": {"center": [0, 0, 0], "radius": 1.0}}, "density": cone,
                          "sigma_t": 4.0, "albedo": 1.0, "phase": {"hg": {"g": 0.5}}}],
             "path": {"bounces": 256, "samples": 256}}
    out = tv.render([scene] * seeds, seed=list(range(seeds)))
    f = (size / 2) / math.tan(math.radians(fov) / 2)
    centre = torch.arange(size, dtype=F64) + 0.5 - size / 2
    cos = f / torch.sqrt(f * f + centre[:, None] ** 2 + centre[None, :] ** 2)
    irradiance = (out.radiance.double().mean(dim=1) * cos**4 / f**2).sum(dim=(1, 2))
    mean, error = _mean_and_error(irradiance)
    expected = (1.0 - math.exp(-2.0)) / distance**2
    assert abs(mean - expected) <= 5.0 * error and error < 0.025 * expected, (  # collision next events: 4%
        f"point light's furnace: {mean:.5g} ± {error:.2g} against (1 − e^(−τ))·I/D² = {expected:.5g}")


@pytest.mark.parametrize("view", ["ground", "space"])
def test_one_bounce_is_the_marched_single_scattering_of_the_atmosphere(view, one_thread):
    """The `[atmosphere]`'s air as two media (Rayleigh of each path's colour, Mie) over the planet's
    Lambertian ground: one bounce is the march's single scattering (fine steps) at sunset from the
    ground and over the limb from space (the ground lit through the air)."""
    scene = tv.preset("atmosphere", width=6, height=6, **({"view": view} if view != "space" else {})).model_dump()
    scene["atmosphere"].update(steps=256, light_steps=64)
    _single_scattering_check(scene, samples=96)


def test_the_air_traces_alike_in_the_kernel_and_eagerly(one_thread):
    """The air's media and the ground from the same lanes in both backends, each path's colour
    stratified (`hero_channels`): the same image up to float rounding."""
    pytest.importorskip("drjit")
    scene = tv.preset("atmosphere", width=6, height=6, view="air").model_dump()
    scene["path"] = {"bounces": 8, "samples": 6}
    kernel, eager = tv.render(scene), tv.render(scene, compile="off")
    assert kernel.stats["plan"]["path"]["backend"] == "drjit"
    gap = (kernel.radiance - eager.radiance).abs()
    assert float(gap.max()) < 1e-3 * float(eager.radiance.max()), f"kernel and eager differ by up to {float(gap.max()):.3g}"


@pytest.mark.parametrize("name", ["cloud-puff", "terrain-clouds", "atmosphere"])
def test_the_march_gives_single_scattering_and_the_paths_the_rest(name, one_thread):
    """`single = "march"`: the march's single scattering (its octaves and ambient dropped, as for
    every `[path]` render) plus the paths' orders past the first. One bounce with no sky leaves the
    paths nothing: exactly the march. Every order agrees with every order path-traced within the
    noise of the two (image means of independent seeds); in the thin air the pixels' noise falls
    by more than half (the march's in-scatter needs no collision)."""
    scene = tv.preset(name, width=8, height=8).model_dump()
    if scene["sky"] is None:
        march = tv.render(scene)  # (the atmosphere preset has no stand-ins to drop)
        one = tv.render({**scene, "path": {"bounces": 1, "samples": 4, "single": "march"}})
        assert torch.equal(one.radiance, march.radiance)
    seeds, images = 6, {}
    for single in ("paths", "march"):
        batch = tv.render([{**scene, "path": {"bounces": 64, "samples": 8, "single": single}}] * seeds, seed=list(range(seeds)))
        assert batch.stats["plan"]["path"]["single"] == single
        images[single] = batch.radiance.double()
    (a, ea), (b, eb) = (_mean_and_error(images[k].mean(dim=(1, 2, 3))) for k in ("paths", "march"))
    assert abs(a - b) <= 5.0 * math.hypot(ea, eb), f"{name}: every order path-traced {a:.5g} ± {ea:.2g}, on the march {b:.5g} ± {eb:.2g}"
    if name == "atmosphere":
        noise = {k: float(v.std(dim=0).mean() / v.mean()) for k, v in images.items()}
        assert noise["march"] < 0.6 * noise["paths"], f"pixel noise on the march {noise['march']:.3f}, path-traced {noise['paths']:.3f}"


def test_a_thin_layer_in_a_wide_box_is_tracked(one_thread):
    """The cloudscape's shell (a 2.5-unit layer over a planet 1000 in radius) in a box its 24³
    lattice samples miss: its declared bound (`DENSITIES`' ``bound``) is the majorant. Its
    transmittance, path-traced through an absorbing copy under a constant sky, is the field's own
    along each pixel's ray (dense quadrature, float64), horizon pixels included."""
    scene = tv.preset("cloudscape", width=6, height=6).model_dump()
    scene.update(sky={"kind": "constant", "radiance": [1.0, 1.0, 1.0]}, lights=[{"direction": [0, 1, 0], "intensity": 0.0}])
    scene["image"]["spp"] = 1
    scene["volumes"][0].update(albedo=0.0, ambient=None, multiple_scattering=None, sky_blend=None)  # the field alone
    seeds = 4
    traced = tv.render([{**scene, "path": {"bounces": 1, "samples": 64}}] * seeds, seed=list(range(seeds)), keep_context=True)
    ctx = traced.context
    rays = camera_for(ctx.batch).ray_range(0, 36, spp=1)
    vol = ctx.volumes[0]
    near, far = (t.double() for t in vol.intersect(rays.origins, rays.directions, rays.scene_index))
    crosses = far > near.clamp_min(0.0)
    t0 = torch.where(crosses, near.clamp_min(0.0), torch.zeros_like(near))
    t1 = torch.where(crosses, far, torch.zeros_like(far))
    u = torch.linspace(0.0, 1.0, 4001, dtype=F64)
    t = t0[:, None] + u[None, :] * (t1 - t0)[:, None]  # [36, 4001]
    points = rays.origins.double()[:, None, :] + t[..., None] * rays.directions.double()[:, None, :]
    density = vol.field(points.reshape(-1, 3).float(), torch.zeros(points.shape[0] * points.shape[1], dtype=torch.long))
    tau = torch.trapezoid(float(vol.params.sigma_t[0]) * density.double().reshape(t.shape), t, dim=1)
    expected = float(torch.exp(-tau).mean())
    mean, error = _mean_and_error(traced.radiance.double()[:, 0].mean(dim=(1, 2)))
    assert traced.stats["path"]["above_majorant"] == 0
    assert abs(mean - expected) <= 5.0 * error + 1e-3, f"path-traced transmittance {mean:.4f} ± {error:.2g}, the field's {expected:.4f}"


def test_every_order_adds_light_and_the_plan_says_so(one_thread):
    grid = puff_grid(12)
    scene = torchvol_scene(grid, sigma_for(grid, 6.0), size=5, spp=1)
    one = tv.render({**scene, "path": {"bounces": 1, "samples": 16}}, dtype=F64)
    every = tv.render({**scene, "path": {"bounces": 64, "samples": 16}}, dtype=F64)
    assert float(every.radiance.mean()) > 1.5 * float(one.radiance.mean())
    assert every.stats["plan"]["path"] == {"bounces": 64, "samples": 16, "backend": "eager", "single": "paths"}
    assert "path" in every.stats["passes"] and every.stats["path"]["truncated"] == 0


def test_paths_alone_run_the_march_unlit(one_thread):
    """With `single = "paths"` the paths give all the light: the march runs unlit (no shadow pass of
    the volume or the terrain; the stats say so), and its depth and alpha are the lit march's."""
    scene = tv.preset("terrain-clouds", width=8, height=6).model_dump()
    lit = tv.render(scene)
    traced = tv.render({**scene, "path": {"bounces": 2, "samples": 1}})
    assert {"volume0.shadow0", "terrain.shadow0"} <= set(lit.stats["passes"])
    assert not [p for p in traced.stats["passes"] if "shadow" in p], traced.stats["passes"]
    assert torch.equal(traced.depth, lit.depth) and torch.equal(traced.alpha, lit.alpha)
    on_march = tv.render({**scene, "path": {"bounces": 2, "samples": 1, "single": "march"}})
    assert "volume0.shadow0" in on_march.stats["passes"]


def test_a_batch_renders_each_scene_as_alone(one_thread):
    scene = _furnace(0.8, 8, samples=4)
    scene["lights"] = [{"direction": [0.3, 1.0, 0.2], "intensity": 2.0}]
    scene["volumes"][0]["bounds"] = {"box": {"min": [-1, -1, -1], "max": [1, 1, 3]}}
    other = {**scene, "volumes": [{**scene["volumes"][0], "sigma_t": 0.7}]}
    batch = tv.render([scene, other], seed=[3, 5])
    for b, (sc, seed) in enumerate(((scene, 3), (other, 5))):
        alone = tv.render(sc, seed=seed)
        assert torch.equal(batch.radiance[b], alone.radiance[0]), f"scene {b} differs alone"
    again = tv.render(scene, seed=4)
    assert not torch.equal(again.radiance, tv.render(scene, seed=3).radiance)  # the seed drives the paths


def _differing(name: str) -> tuple[dict, dict]:
    """Two scenes of one structure, at an odd size, whose per-scene values differ: the terrain's
    seed and colour and a point light's position, or the air's coefficients, ground and sun."""
    scene = tv.preset(name, width=9, height=5, **({"view": "ground"} if name == "atmosphere" else {})).model_dump()
    scene["path"] = {"bounces": 5, "samples": 2}
    other = copy.deepcopy(scene)
    if name == "terrain-clouds":
        for sc, x in ((scene, 1.0), (other, -2.0)):
            sc["lights"].append({"kind": "point", "position": [x, 2.0, 1.0], "intensity": 20.0})
        other["terrain"].update(seed=11, color=[0.5, 0.2, 0.1])
        other["volumes"][0]["sigma_t"] = 9.0
    else:
        other["atmosphere"].update(ground=[0.6, 0.5, 0.4], mie=5e-5, rayleigh=[1e-5, 2e-5, 4e-5])
        other["lights"][0]["direction"] = [0.0, 0.02, 1.0]
    return scene, other


@pytest.mark.parametrize("name", ["terrain-clouds", "atmosphere"])
def test_surfaces_and_air_render_each_scene_of_a_batch_as_alone(name, one_thread):
    scenes = _differing(name)
    batch = tv.render(list(scenes), seed=[3, 5])
    for b, (sc, seed) in enumerate(zip(scenes, (3, 5))):
        alone = tv.render(sc, seed=seed)
        assert torch.equal(batch.radiance[b], alone.radiance[0]), f"{name}: scene {b} differs alone"
    assert not torch.equal(batch.radiance[0], batch.radiance[1])


@pytest.mark.slow
@settings(max_examples=12, deadline=None)
@given(sigma=st.sampled_from([0.0, 1e-3, 1.0, 50.0, 1e4, 1e7]), albedo=st.sampled_from([0.0, 0.5, 1.0]),
       g=st.sampled_from([-0.999, -0.5, 0.0, 0.9, 0.999]), kind=st.sampled_from(["hg", "dual_hg", "mie", "rayleigh", "isotropic"]),
       density=st.sampled_from([{"constant": 1.0}, {"exponential": {"value": 1.0, "base": -1.0, "scale_height": 0.3}}]))
def test_random_media_give_finite_images(sigma, albedo, g, kind, density):
    phase = {"hg": {"hg": {"g": g}}, "mie": {"mie": {"g": g}}, "rayleigh": "rayleigh", "isotropic": "isotropic",
             "dual_hg": {"dual_hg": {"g_forward": abs(g), "g_backward": -abs(g), "weight": 0.3}}}[kind]
    scene = {"image": {"width": 3, "height": 3}, "camera": {"eye": [0, 0, -3], "target": [0, 0, 0], "fov_y": 50},
             "sky": {"kind": "constant", "radiance": [0.2, 0.3, 0.5]},
             "lights": [{"direction": [0.2, 1.0, -0.3], "intensity": 3.0},
                        {"kind": "point", "position": [0.0, 0.5, 0.0], "intensity": 1.0}],
             "volumes": [{"bounds": {"box": {"min": [-1, -1, -1], "max": [1, 1, 1]}}, "density": density,
                          "sigma_t": sigma, "albedo": albedo, "phase": phase, "emission": [0.1, 0.1, 0.1]}],
             "path": {"bounces": 6, "samples": 2}}
    out = tv.render(scene)
    assert torch.isfinite(out.radiance).all() and torch.isfinite(out.image).all()
    assert out.stats["path"]["truncated"] == 0


@pytest.mark.slow
@settings(max_examples=16, deadline=None)
@given(surface=st.sampled_from(["terrain", "atmosphere", "voxels", "voxels+terrain", "terrain+atmosphere"]),
       sigma=st.sampled_from([0.0, 1e-3, 2.0, 1e4, 1e7]),
       albedo=st.sampled_from([0.0, 0.7, 1.0]), g=st.sampled_from([-0.999, 0.0, 0.999]),
       sun_y=st.sampled_from([-0.3, 0.0, 1e-4, 1.0]), single=st.sampled_from(["paths", "march"]),
       point=st.sampled_from([None, [0.0, -0.5, 0.0], [0.0, 0.8, 0.0]]))
def test_random_surfaces_and_air_give_finite_images(surface, sigma, albedo, g, sun_y, single, point):
    """A medium over the terrain (flat to steep, the sun grazing or below it, a point light under
    the ground or in the medium), over voxels (an emitting block through the medium's box), both,
    or in the air over the planet (a terrain under it or not): finite, non-negative radiance,
    depth ≥ 0, whatever the density, albedo, phase and `single`."""
    scene = {"image": {"width": 4, "height": 3}, "camera": {"eye": [0, 1.5, -3], "target": [0, 0, 0], "fov_y": 60},
             "lights": [{"direction": [0.3, sun_y, 0.2], "intensity": 3.0}]
             + ([{"kind": "point", "position": point, "intensity": 2.0}] if point is not None else []),
             "volumes": [{"bounds": {"box": {"min": [-1, 0.2, -1], "max": [1, 1.2, 1]}}, "density": {"constant": 1.0},
                          "sigma_t": sigma, "albedo": albedo, "phase": {"hg": {"g": g}}}],
             "path": {"bounces": 6, "samples": 2, "single": single}}
    if "terrain" in surface:
        scene["terrain"] = {"amplitude": 0.0 if sigma < 1.0 else 2.0, "frequency": 1.5, "steps": 32}
    if "voxels" in surface:
        scene["voxels"] = {"occupancy": {"sdf": {"shape": {"box": {"center": [0.0, 0.5, 0.0], "half_size": [0.5, 1.0, 0.5]}},
                                                 "material": 1}},
                           "cells": {"min": [-2, -1, -2], "max": [2, 2, 2]}, "voxel_size": 0.5,
                           "materials": [{"color": [albedo] * 3, "emission": [0.3, 0.2, 0.1]}]}
    if "atmosphere" in surface:
        scene["atmosphere"] = {"planet_radius": 6.36e6, "atmosphere_height": 6e4}
    else:
        scene["sky"] = {"kind": "constant", "radiance": [0.2, 0.3, 0.5]}
    out = tv.render(scene)
    assert torch.isfinite(out.radiance).all() and (out.radiance >= 0).all(), "non-finite or negative radiance"
    assert (out.depth >= 0).all() and torch.isfinite(out.image).all()


def _two_suns_over_a_cloud(phase: dict, ground: bool) -> dict:
    """A grid puff (optical depth 4) lit by two suns, over flat ground or in the void."""
    grid = puff_grid(12)
    scene = torchvol_scene(grid, sigma_for(grid, 4.0), size=6, spp=1, shadow_steps=64)
    scene["volumes"][0]["phase"] = phase
    scene["lights"] = [{"direction": [0.8, 0.3, -0.5], "intensity": 2.0}, {"direction": [-0.2, 1.0, 0.6], "intensity": 1.5}]
    if ground:
        low = scene["volumes"][0]["bounds"]["box"]["min"][1]
        scene["terrain"] = {"amplitude": 0.0, "base": low - 0.3, "color": [0.5] * 3, "rock_color": [0.5] * 3, "steps": 16}
    return scene


def _flights_and_plain(scene: dict, seeds: int, monkeypatch) -> list[tuple[float, float]]:
    """The mean radiance of `seeds` independent images and its standard error (from the pixels'
    variance over the images), with the suns' next events by flights (`path._suns_next`) and plain."""
    from torchvol.volume import path

    out = []
    for flights in (True, False):
        monkeypatch.setattr(path, "SUN_FLIGHTS", flights)
        traced = tv.render([scene] * seeds, seed=list(range(seeds))).radiance.double()
        out.append((float(traced.mean()), float(traced.var(dim=0).mean().sqrt()) / math.sqrt(traced.numel())))
    return out


@pytest.mark.parametrize(("phase", "ground"), [({"hg": {"g": 0.5}}, False), ("rayleigh", False),
                                               pytest.param({"mie": {"g": 0.7}}, True, marks=pytest.mark.slow),
                                               pytest.param({"dual_hg": {"g_forward": 0.9, "g_backward": -0.4, "weight": 0.3}}, True,
                                                            marks=pytest.mark.slow)])
def test_the_suns_next_events_by_flights_are_the_plain_next_events(phase, ground, one_thread, monkeypatch):
    """The suns' next events of a collision's successor, taken by a flight of their own drawn
    towards the suns (`path._suns_next`), estimate what the plain next events at each collision
    do: two suns, orders 2 to 3, every phase kind's sampling, over a ground that stops flights or
    not; the means of independent images within five standard errors of each other."""
    (flights, e1), (plain, e2) = _flights_and_plain({**_two_suns_over_a_cloud(phase, ground),
                                                    "path": {"bounces": 3, "samples": 256}}, 4, monkeypatch)
    error = math.hypot(e1, e2)
    assert abs(flights - plain) <= 5.0 * error, f"{phase}: flights {flights:.6g}, plain {plain:.6g} (standard error {error:.2g})"
    assert error < 0.02 * plain  # the check is sharp enough to fail


def test_flights_towards_a_sun_take_the_noise_of_a_peaked_phase_function(one_thread, monkeypatch):
    """HG 0.9, the second order alone as the flights take it: their noise is under half the plain
    next events' (which meet the phase function's peak only where a path flies towards the sun)."""
    scene = {**_two_suns_over_a_cloud({"hg": {"g": 0.9}}, False), "path": {"bounces": 2, "samples": 64}}
    scene["lights"] = scene["lights"][:1]
    (_, flights), (_, plain) = _flights_and_plain(scene, 4, monkeypatch)
    assert flights < 0.5 * plain, f"the flights' standard error {flights:.3g}, the plain next events' {plain:.3g}"


@pytest.mark.parametrize("g", [-0.999, -0.6, 0.0, 0.3, 0.95, 0.999])
def test_hg_samples_follow_the_phase_function(g):
    """The drawn cosines' mean is HG's mean cosine g, and a histogram matches the density."""
    u = (torch.arange(200_000, dtype=F64) + 0.5) / 200_000
    cos = hg_cos(torch.full_like(u, g), u)
    assert abs(float(cos.mean()) - g) < 2e-3
    assert float(cos.min()) >= -1.0 and float(cos.max()) <= 1.0


def _over_flat_ground(medium: dict, *, albedo: float = 0.4, sky: float = 0.0) -> dict:
    """A flat terrain of one colour (`albedo`, no ambient) under a slanted sun, a camera looking
    down at it at 45°, `medium` a box over the ground, a constant sky of radiance `sky`."""
    return {"image": {"width": 6, "height": 6}, "camera": {"eye": [0, 3, -3], "target": [0, 0, 0], "fov_y": 30},
            "sky": {"kind": "constant", "radiance": [sky] * 3},
            "lights": [{"direction": [0.3, 1.0, 0.2], "intensity": 2.0, "shadow": {"steps": 64}}],
            "terrain": {"amplitude": 0.0, "color": [albedo] * 3, "rock_color": [albedo] * 3, "ambient": [sky] * 3,
                        "steps": 16},
            "volumes": [{"bounds": {"box": {"min": [-2, 0.3, -2], "max": [2, 1.3, 2]}}, **medium}],
            "march": {"quality": "high", "steps": 192, "closed_form": False}}


def test_flat_ground_under_a_sun_and_a_sky_is_lambert_shaded():
    """No medium (zero density): every path meets the ground, takes the sun's a·E·cos θ (the
    surfaces' convention, as the marched terrain and voxel GI shade) and bounces into the constant
    sky S, which it sees whatever its direction: a·(E·cos θ + S), exact for any bounce count, as
    the marched terrain with `ambient` S gives it."""
    a, sky = 0.4, 0.25
    scene = _over_flat_ground({"density": {"constant": 0.0}, "sigma_t": 1.0}, albedo=a, sky=sky)
    cos = 1.0 / math.sqrt(0.3**2 + 1.0 + 0.2**2)
    expected = a * (2.0 * cos + sky)
    for bounces in (1, 4):
        out = tv.render({**scene, "path": {"bounces": bounces, "samples": 2}}, dtype=F64)
        assert_close(out.radiance, expected, atol=1e-9, what=f"path-traced ground, {bounces} bounces")
    assert_close(tv.render(scene, dtype=F64).radiance, expected, atol=1e-9, what="marched ground")


def test_one_bounce_over_the_ground_is_the_marched_single_scattering(one_thread):
    """A cloud over the ground, lit by a sun: with one bounce the paths take the cloud's single
    scattering and the ground's direct light through the cloud's shadow, as the march does."""
    _single_scattering_check(_over_flat_ground({"density": {"constant": 1.0}, "sigma_t": 1.2, "albedo": 0.8,
                                                "phase": {"hg": {"g": 0.5}}}), samples=48)


def test_the_ground_shadows_and_bounces_paths(one_thread):
    """A pure absorber over the ground: nothing scatters in it, so the ground seen through it and
    lit through it is all there is, and every order equals the marched render; the kernel draws the
    same paths as eager."""
    pytest.importorskip("drjit")
    scene = _over_flat_ground({"density": {"constant": 1.0}, "sigma_t": 0.8, "albedo": 0.0})
    march = float(tv.render(scene, dtype=F64).radiance.mean())
    traced = {mode: tv.render({**scene, "path": {"bounces": 8, "samples": 64}}, compile=mode) for mode in ("kernels", "off")}
    assert traced["kernels"].stats["plan"]["path"]["backend"] == "drjit"
    mean, error = _mean_and_error(traced["off"].radiance.mean(dim=1))
    assert abs(mean - march) <= 5.0 * error and error < 0.05 * march, f"path {mean:.5g} ± {error:.2g}, march {march:.5g}"
    gap = (traced["kernels"].radiance - traced["off"].radiance).abs()
    assert float(gap.max()) < 1e-4, f"kernel and eager paths differ by up to {float(gap.max()):.3g}"


def test_path_tracing_refuses_what_it_cannot_trace_yet():
    looks = _furnace(0.5, 2)
    looks["volumes"][0]["shading"] = "shader"
    with pytest.raises(SceneError, match="path"):
        tv.render(looks)


def test_a_terrain_under_the_air_is_the_marched_single_scattering(one_thread):
    """The terrain and the planet's ground together (`path.surfaces`, the terrain over the ground as
    the march puts it): one bounce at sunset from the ground is the march's single scattering (the
    air's, the terrain's direct light through it)."""
    scene = tv.preset("atmosphere", width=6, height=6, view="air").model_dump()
    scene["camera"].update(eye=(0.0, 2000.0, 0.0), target=(0.0, 0.0, 8000.0))  # 2 km up, the terrain ahead
    scene["atmosphere"].update(steps=256, light_steps=64)
    scene["terrain"] = {"amplitude": 300.0, "frequency": 0.0005, "color": [0.3, 0.25, 0.2], "rock_color": [0.3, 0.25, 0.2],
                        "ambient": [0.0, 0.0, 0.0], "steps": 256, "max_distance": 50000.0}
    _single_scattering_check(scene, samples=160, dtype=torch.float32)  # (the kernels: eagerly it takes 80 s)


def test_the_kernel_tracks_as_eager_does(one_thread):
    """The tracking as a Dr.Jit kernel (float32 on the CPU) and eagerly: the same lanes function and
    the same draws, so the same paths up to float rounding; the plan says which ran. (Under a
    sky, blended into it with distance: `sky_blend`'s share taken alike.)"""
    pytest.importorskip("drjit")
    grid = puff_grid(12)
    scene = torchvol_scene(grid, sigma_for(grid, 6.0), size=6, spp=1)
    scene["path"] = {"bounces": 16, "samples": 16}
    scene["sky"] = {"kind": "gradient", "horizon": [0.9, 0.6, 0.3], "slope": [-0.5, 0.0, 0.6]}
    scene["volumes"][0]["sky_blend"] = 0.02
    kernel, eager = tv.render(scene), tv.render(scene, compile="off")
    assert kernel.stats["plan"]["path"]["backend"] == "drjit" and eager.stats["plan"]["path"]["backend"] == "eager"
    gap = (kernel.radiance - eager.radiance).abs()
    assert float(gap.mean()) < 1e-3 * float(eager.radiance.mean()), f"kernel and eager paths differ by {float(gap.mean()):.3g} on average"
    # the paths' own evaluations (each render's total less its march's, which runs unlit: the
    # paths give all the light), counted alike
    unlit = {**{k: v for k, v in scene.items() if k != "path"}, "lights": []}
    marched = {mode: tv.render(unlit, compile=mode).stats["density_evals"] for mode in ("kernels", "off")}
    traced = kernel.stats["density_evals"] - marched["kernels"], eager.stats["density_evals"] - marched["off"]
    assert traced[0] > 0 and traced[0] == pytest.approx(traced[1], rel=1e-3)


PATH_PRESETS = ["cloud-puff", "homogeneous-box", "explosion", "fire", "cloudscape", "multi-layer", "particles", "god-rays",
                "terrain-clouds", "atmosphere"]
REFUSED = {"fur-ball": "shading", "template-clouds": "shading"}


@pytest.mark.parametrize("name", PATH_PRESETS + sorted(REFUSED))
def test_every_preset_with_physical_media_path_traces(name, one_thread):
    """The presets whose media are physical render with `[path]` (finite, the plan saying so);
    the others are refused at the boundary, naming `path` and why."""
    scene = tv.preset(name, width=6, height=6).model_dump()
    scene["path"] = {"bounces": 4, "samples": 1}
    if name in REFUSED:
        with pytest.raises(SceneError, match=f"path.*{REFUSED[name]}"):
            tv.render(scene)
        return
    out = tv.render(scene)
    assert torch.isfinite(out.radiance).all() and float(out.radiance.sum()) > 0
    assert out.stats["plan"]["path"]["bounces"] == 4 and "path" in out.stats["passes"]


@pytest.mark.parametrize("compile_mode", ["kernels", "off"])
def test_samples_traced_together_give_the_bytes_of_one_at_a_time(compile_mode, one_thread, monkeypatch):
    """A chunk's samples run as one batch of paths (`path.PATH_LANES`): each path's draws are its
    own and the samples are summed in order, so the image's bytes are those of one sample a call."""
    from torchvol.volume import path

    grid = puff_grid(12)
    scene = torchvol_scene(grid, sigma_for(grid, 6.0), size=6, spp=2)
    scene["path"] = {"bounces": 32, "samples": 7}
    scene["sky"] = {"kind": "gradient", "horizon": [0.9, 0.6, 0.3], "slope": [-0.5, 0.0, 0.6]}
    together = tv.render(scene, compile=compile_mode).radiance
    for lanes in (1, 150):  # one sample a call; two samples (72 rays each) a call, the last alone
        monkeypatch.setattr(path, "PATH_LANES", lanes)
        assert torch.equal(tv.render(scene, compile=compile_mode).radiance, together), f"{lanes} paths a call"
