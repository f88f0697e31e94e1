"""Per-medium labels (torchvol.renderer.labels): optical thickness, per-volume alpha, instance ids and sun
visibility against closed forms, computed only when asked for, batched as alone, and carried by
SceneDataset, generate and FolderDataset.

Expected values are rebuilt independently in numpy float64 from the exported camera (the rays and
chords of tests/volume/test_analytic.py); silhouette pixels, where a chord is ill-conditioned,
are left out by `well_conditioned`."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import TOL, assert_close
from volume.test_analytic import (
    box_interval,
    camera_rays,
    slab_interval,
    sphere_interval,
    up_for,
    well_conditioned,
)

import torchvol as tv
from torchvol.dataset.generate import generate

LABELS = ["optical_thickness", "alpha_volumes", "instance", "sun_visibility"]
SUN = [{"kind": "sun", "direction": [0.0, 1.0, 0.0]}]


def scene(volumes, *, eye=(0.0, 0.0, -4.0), target=(0.0, 0.0, 0.0), width=16, height=12, fov=40.0, **extra):
    return {"image": {"width": width, "height": height},
            "camera": {"eye": list(eye), "target": list(target), "up": up_for(eye, target), "fov_y": fov},
            "lights": SUN, "volumes": volumes, **extra}


def sphere(center, radius, sigma, **kw):
    return {"bounds": {"sphere": {"center": list(center), "radius": radius}}, "density": {"constant": 1.0},
            "sigma_t": sigma, **kw}


def box(lo, hi, sigma, **kw):
    return {"bounds": {"box": {"min": list(lo), "max": list(hi)}}, "density": {"constant": 1.0}, "sigma_t": sigma, **kw}


def chord(interval, eye, dirs, *args):
    t0, t1, hit = interval(eye, dirs, *args)
    return np.where(hit, t1 - t0, 0.0)


@pytest.mark.parametrize("closed_form", [True, False])
def test_optical_thickness_through_a_homogeneous_sphere_is_sigma_times_the_chord(closed_form, one_thread):
    sigma, r = 3.0, 1.0
    s = scene([sphere((0, 0, 0), r, sigma)], march={"closed_form": closed_form, "steps": 8})
    out = tv.render(s, aovs=["optical_thickness"])
    assert ("volume0.closed_form" in out.stats["passes"]) == closed_form
    eye, dirs, _ = camera_rays(out)
    # the closed form 2·sqrt(r² − b²), b the ray's distance from the centre
    b2 = (np.cross(-np.asarray(eye), dirs) ** 2).sum(-1)
    expected = sigma * 2.0 * np.sqrt(np.clip(r * r - b2, 0.0, None))
    ok = well_conditioned(lambda e, d: sigma * chord(sphere_interval, e, d, (0, 0, 0), r), eye, dirs, tol=1e-4)
    tau = out.aovs["optical_thickness"][0, 0].double().numpy()
    assert ok.mean() > 0.8 and (expected[ok] > 0).sum() > 20
    rel = np.abs(tau - expected)[ok] / np.maximum(expected[ok], 1.0)
    assert rel.max() < 1e-5, rel.max()


def test_optical_thickness_through_a_slab_and_unbounded(one_thread):
    sigma = 400.0  # τ in the hundreds: beyond what float32 transmittance can hold, the label is not capped
    s = scene([{"bounds": {"slab": {"y_min": -1.0, "y_max": -0.5}}, "density": {"constant": 1.0}, "sigma_t": sigma}],
              eye=(0.0, 1.0, -3.0), target=(0.0, -1.0, 0.0), march={"steps": 4})
    out = tv.render(s, aovs=["optical_thickness"])
    eye, dirs, _ = camera_rays(out)
    expected = sigma * chord(slab_interval, eye, dirs, -1.0, -0.5)
    tau = out.aovs["optical_thickness"][0, 0].double().numpy()
    assert expected.min() > 200 and (out.alpha == 1).all()
    assert_close(torch.from_numpy(tau / expected), 1.0, atol=1e-5, what="τ / σ·chord")


def test_optical_thickness_from_inside_a_sphere_is_sigma_times_the_radius(one_thread):
    out = tv.render(scene([sphere((0, 0, 0), 2.0, 1.5)], eye=(0.0, 0.0, -0.5), march={"closed_form": False, "steps": 4}),
                    aovs=["optical_thickness", "instance", "sun_visibility"])
    eye, dirs, _ = camera_rays(out)
    expected = 1.5 * chord(sphere_interval, eye, dirs, (0, 0, 0), 2.0)  # from the eye to the exit
    assert_close(out.aovs["optical_thickness"][0, 0] / torch.from_numpy(expected).float(), 1.0, atol=1e-5, what="τ / σ·(exit − eye)")
    assert (out.aovs["instance"] == 1).all() and torch.isfinite(out.aovs["sun_visibility"]).all()


def test_optical_thickness_adds_over_disjoint_volumes(one_thread):
    a = sphere((-0.6, 0, 0), 0.5, 2.0)
    b = box((-0.2, -0.4, 1.0), (1.2, 0.6, 1.5), 1.5, density={"fbm": {"octaves": 2, "frequency": 2.0}})
    taus = [tv.render(scene(v, march={"steps": 8}), aovs=["optical_thickness"]).aovs["optical_thickness"]
            for v in ([a], [b], [a, b])]
    assert taus[0].max() > 0 and taus[1].max() > 0
    assert_close(taus[2], taus[0] + taus[1], atol=1e-5, what="τ(a, b) − τ(a) − τ(b)")


def two_spheres():
    return scene([sphere((-0.8, 0, 0), 0.6, 4.0), sphere((0.8, 0, 0), 0.6, 4.0)], width=24, height=12)


def test_instance_and_volume_alphas_on_two_disjoint_volumes(one_thread):
    out = tv.render(two_spheres(), aovs=["alpha_volumes", "instance"])
    eye, dirs, _ = camera_rays(out)
    alphas = np.stack([1.0 - np.exp(-4.0 * chord(sphere_interval, eye, dirs, (x, 0, 0), 0.6)) for x in (-0.8, 0.8)])
    av = out.aovs["alpha_volumes"][0].double().numpy()
    assert av.shape == (2, 12, 24)
    assert_close(out.aovs["alpha_volumes"].sum(dim=1, keepdim=True), out.alpha, what="Σ alpha_volumes − alpha")
    ok = well_conditioned(lambda e, d: 1.0 - np.exp(-4.0 * chord(sphere_interval, e, d, (-0.8, 0, 0), 0.6)), eye, dirs)
    ok &= well_conditioned(lambda e, d: 1.0 - np.exp(-4.0 * chord(sphere_interval, e, d, (0.8, 0, 0), 0.6)), eye, dirs)
    assert_close(torch.from_numpy(av[:, ok]), torch.from_numpy(alphas[:, ok]), atol=1e-5, what="alpha of each sphere")
    # each pixel sees one sphere: the largest of (sky's transmittance, alpha 1, alpha 2)
    expected = np.argmax(np.stack([1.0 - alphas.sum(0), *alphas]), axis=0)
    ids = out.aovs["instance"][0, 0].numpy()
    margin = np.abs(alphas.max(0) - (1.0 - alphas.sum(0))) > 1e-3  # not a tie between sky and sphere
    assert np.array_equal(ids[ok & margin], expected[ok & margin])
    assert set(np.unique(ids)) == {0.0, 1.0, 2.0} and ids[0, 0] == 0 and ids[6, 12] == 0  # background between
    assert {frozenset(np.unique(ids[:, :12]).tolist()), frozenset(np.unique(ids[:, 12:]).tolist())} == {frozenset({0.0, 1.0}), frozenset({0.0, 2.0})}


def test_volume_alphas_follow_the_composite_where_volumes_overlap(one_thread):
    s = scene([sphere((0, 0, 0), 0.7, 2.0), box((-0.3, -0.3, -0.3), (0.9, 0.9, 0.9), 1.0)])
    out = tv.render(s, aovs=["alpha_volumes"])
    assert_close(out.aovs["alpha_volumes"].sum(dim=1, keepdim=True), out.alpha, what="Σ alpha_volumes − alpha")
    assert (out.aovs["alpha_volumes"] >= 0).all()


def test_sun_visibility_inside_and_behind_homogeneous_boxes(one_thread):
    sa, sb = 2.0, 5.0
    below = box((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5), sb)  # the depth point: where T crosses 0.5 in it
    above = box((-0.6, 1.0, -0.6), (0.6, 1.4, 0.6), sa)  # the sun (+y) shines through it
    out = tv.render(scene([below, above], fov=20.0), aovs=["sun_visibility"])
    eye, dirs, _ = camera_rays(out)
    t0, t1, hit = box_interval(eye, dirs, (-0.5, -0.5, -0.5), (0.5, 0.5, 0.5))
    crosses = hit & (sb * (t1 - t0) > math.log(2.0))
    p_y = eye[1] + (t0 + math.log(2.0) / sb) * dirs[..., 1]
    # every such point lies under the whole upper box; the sky's pixels see 1
    expected = np.where(crosses, np.exp(-sb * (0.5 - p_y) - sa * 0.4), 1.0)
    ok = well_conditioned(lambda e, d: chord(box_interval, e, d, (-0.5, -0.5, -0.5), (0.5, 0.5, 0.5)), eye, dirs, tol=1e-4)
    vis = out.aovs["sun_visibility"][0, 0].double().numpy()
    assert crosses[ok].sum() > 20 and (~crosses[ok]).sum() > 10
    assert_close(torch.from_numpy(vis[ok]), torch.from_numpy(expected[ok]), atol=2e-5, what="sun visibility")
    assert "labels.sun_visibility.volume1" in out.stats["passes"]


def test_sun_visibility_needs_a_sun():
    s = scene([sphere((0, 0, 0), 0.5, 1.0)])
    s["lights"] = [{"kind": "point", "position": [0, 2, 0]}]
    with pytest.raises(ValueError, match="^aovs: got 'sun_visibility'; needs lights\\[0\\] to be a sun"):
        tv.render(s, aovs=["sun_visibility"])
    with pytest.raises(ValueError, match="^aovs: "):
        tv.render(s, aovs=["not_a_label"])


def test_a_label_nobody_asks_for_costs_nothing(one_thread):
    s = scene([sphere((-0.3, 0, 0), 0.6, 2.0, density={"fbm": {"octaves": 2}}), sphere((0.5, 0, 0.5), 0.5, 1.0)])
    plain, labelled = tv.render(s), tv.render(s, aovs=LABELS)
    assert not any(p.startswith("labels") for p in plain.stats["passes"] + plain.stats["plan"]["passes"])
    assert not set(LABELS) & set(plain.aovs)
    assert [p for p in labelled.stats["passes"] if not p.startswith("labels")] == plain.stats["passes"]
    assert set(labelled.stats["passes"]) <= set(labelled.stats["plan"]["passes"])
    for key in ("image", "radiance", "depth", "alpha"):
        assert torch.equal(getattr(plain, key), getattr(labelled, key)), key
    assert plain.stats["density_evals"] < labelled.stats["density_evals"]


def test_batched_labels_equal_each_scene_alone(one_thread):
    a = scene([sphere((-0.3, 0, 0), 0.6, 2.0, density={"fbm": {"octaves": 2}}), box((0, -0.5, 0.5), (1, 0.5, 1), 1.0)],
              march={"steps": 8})
    b = scene([sphere((-0.2, 0.1, 0), 0.5, 7.0, density={"fbm": {"octaves": 2, "seed": 3}}), box((0, -0.5, 0), (1, 0.2, 1), 3.0)],
              march={"steps": 8})
    b["lights"] = [{"kind": "sun", "direction": [0.5, 1.0, -0.2]}]
    both = tv.render([a, b], seed=[1, 2], aovs=LABELS)
    for i, (sc, seed) in enumerate(((a, 1), (b, 2))):
        alone = tv.render(sc, seed=seed, aovs=LABELS)
        for key in LABELS:
            assert torch.equal(both.aovs[key][i], alone.aovs[key][0]), key
    assert not torch.equal(both.aovs["optical_thickness"][0], both.aovs["optical_thickness"][1])


def test_labels_flow_through_the_datasets(tmp_path, one_thread):
    recipe = {**two_spheres(), "dataset": {"aovs": LABELS},
              "volumes": [sphere((-0.8, 0, 0), 0.6, {"uniform": [2.0, 6.0]}), sphere((0.8, 0, 0), 0.6, 4.0)]}
    live = tv.SceneDataset(recipe, 2, seed=1)
    item = live[1]
    assert item["optical_thickness"].shape == (1, 12, 24) and item["alpha_volumes"].shape == (2, 12, 24)
    generate(recipe, count=2, out=tmp_path / "ds", seed=1, batch=2)
    folder = tv.FolderDataset(tmp_path / "ds")
    for i in range(2):
        a, b = folder[i], live[i]
        for key in LABELS:  # lossless: float32, instance ids as uint16
            assert a[key].dtype == torch.float32 and torch.equal(a[key], b[key]), key
    with np.load(next((tmp_path / "ds").rglob("*.instance.npz"))) as stored:
        assert stored["instance"].dtype.name == "uint16"


def test_voxel_surfaces_instance_ids_and_sun_visibility_match_their_own_labels(one_thread):
    out = tv.render(tv.preset("voxel-terrain", width=16, height=16), aovs=["instance", "sun_visibility"])
    material, hit = out.aovs["material"], out.aovs["material"] > 0
    assert 0 < hit.float().mean() < 1
    assert torch.equal(out.aovs["instance"], material)  # no volumes: V = 0, ids are the material ids
    assert torch.equal(out.aovs["sun_visibility"][hit], out.aovs["shadow"][hit])  # the surface's own shadow ray
    assert (out.aovs["sun_visibility"][~hit] == 1).all()


def test_sun_visibility_runs_its_shadow_rays_in_the_kernel_where_the_render_does(monkeypatch):
    """The label's shadow rays through an fbm cloud and past the terrain take the surfaces' kernel
    (`kernel_march.surface_shadows`), within the tolerance table of eager's (measured: 7.3e-6 at
    128²; its eager pass took 63 ms of a 119 ms render there, the kernel's 12)."""
    from torchvol.runtime.compilation import drjit_available
    from torchvol.volume import kernel_march

    if not drjit_available():
        pytest.skip("Dr.Jit's LLVM backend is not available")
    scene = tv.preset("terrain-clouds", width=32, height=24)
    eager = tv.render(scene, aovs=["sun_visibility"], compile="off")
    from torchvol.renderer import labels

    for module in (kernel_march, labels):  # every way to the eager pass
        monkeypatch.setattr(module, "occluder_transmittance", lambda *a: pytest.fail("an eager shadow ray"), raising=False)
    kernel = tv.render(scene, aovs=["sun_visibility"])
    vis = eager.aovs["sun_visibility"]
    assert float(vis.min()) < 0.5 < float(vis.max())  # shadowed and lit pixels both
    assert_close(kernel.aovs["sun_visibility"], vis, atol=5 * TOL[torch.float32], what="sun_visibility, kernel against eager")
    assert [n for n in kernel.stats["passes"] if n.startswith("labels.")] == [n for n in eager.stats["passes"] if n.startswith("labels.")]


@pytest.mark.parametrize("name", ["cloud-puff", "multi-layer", "cloudscape", "fur-ball", "god-rays"])
def test_optical_thickness_sums_each_chord_in_the_kernel_where_the_render_does(name, monkeypatch):
    """`kernel_march.chord_density`: each volume's midpoint sum of the label as one Dr.Jit kernel,
    within 5e-5 of τ relative to eager's, the same density evaluations; not a sample of the eager
    loop (cloud-puff's label at 128²: 166 -> 11 ms). Measured: 5.7e-7 or less but for cloudscape
    (τ up to 96): 3.1e-6 on the machine this test was written on, 1.5e-5 on an AVX-512 CPU (torch's
    CPU capability AVX512, 2026-12-08)."""
    from torchvol.renderer import labels
    from torchvol.runtime.compilation import drjit_available

    if not drjit_available():
        pytest.skip("Dr.Jit's LLVM backend is not available")
    scene = tv.preset(name, width=32, height=24)
    eager = tv.render(scene, aovs=["optical_thickness"], compile="off")
    kernels = labels.kernel_march.chord_density
    calls = []
    monkeypatch.setattr(labels.kernel_march, "chord_density", lambda *a: calls.append(a[1].plan.name) or kernels(*a))
    kernel = tv.render(scene, aovs=["optical_thickness"])
    tau = eager.aovs["optical_thickness"]
    assert float(tau.max()) > 0.5
    assert_close(kernel.aovs["optical_thickness"] / tau.clamp_min(1.0), tau / tau.clamp_min(1.0), atol=5e-5,
                 what=f"{name}: τ, kernel against eager")
    assert kernel.stats["density_evals"] == eager.stats["density_evals"]
    assert calls, "no volume's label summed in the kernel"
