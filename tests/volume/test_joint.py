"""Media that share space (torchvol.volume.joint): one march through every medium of a ray.

Along one ray the media are piecewise homogeneous, so the radiance has an exact solution: cut the
ray at every entry and exit, sum σ_t and the source of the media in each piece, and composite
the pieces front to back (`piecewise`). Overlapping partly, fully and nested, emissive, absorbing
and scattering, in every list order, the render matches it; the depth and the per-medium alpha
shares too; a medium split into two identical overlapping halves renders as the whole."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from conftest import assert_close
from hypothesis import given, settings
from hypothesis import strategies as st

import torchvol as tv

SUN = {"kind": "sun", "direction": [0.0, 1.0, 0.0], "color": [1.0, 1.0, 1.0], "intensity": 3.0}
ISOTROPIC = 1.0 / (4.0 * math.pi)


def slab_box(z0, z1, sigma, **kw):
    """A box wide across the view, filling z0..z1 along the axis ray."""
    return {"bounds": {"box": {"min": [-2.0, -2.0, z0], "max": [2.0, 2.0, z1]}}, "density": {"constant": 1.0},
            "sigma_t": sigma, "albedo": 0.0, **kw}


def axis_scene(volumes, *, lights=(), march=None, width=1, height=1):
    """One pixel whose ray runs exactly along +z from z = −5 (the centre of an odd image)."""
    s = {"image": {"width": width, "height": height},
         "camera": {"eye": [0.0, 0.0, -5.0], "target": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0], "fov_y": 10.0},
         "lights": list(lights), "volumes": volumes}
    if march is not None:
        s["march"] = march
    return s


def piecewise(media, eye_z=-5.0):
    """The exact radiance, transmittance, expected distance and each medium's alpha share along the
    +z axis ray through homogeneous `media` [(z0, z1, σ_t, source per unit length)], float64."""
    cuts = sorted({z for m in media for z in m[:2]})
    radiance, trans, wsum, wt = 0.0, 1.0, 0.0, 0.0
    shares = [0.0] * len(media)
    for a, b in zip(cuts[:-1], cuts[1:]):
        here = [i for i, m in enumerate(media) if m[0] <= a and m[1] >= b]
        sigma, source, length = sum(media[i][2] for i in here), sum(media[i][3] for i in here), b - a
        if not here or sigma == 0:
            continue
        seg = math.exp(-sigma * length)
        radiance += trans * source * (1.0 - seg) / sigma
        x = sigma * length  # the expected termination depth inside the piece
        t_mean = (a - eye_z) + length * (1.0 / x - 1.0 / math.expm1(x))
        wsum, wt = wsum + trans * (1.0 - seg), wt + trans * (1.0 - seg) * t_mean
        for i in here:
            shares[i] += trans * (1.0 - seg) * media[i][2] / sigma
        trans *= seg
    return radiance, trans, wt / wsum, shares


def centre(out, what):
    return getattr(out, what)[0, 0, 0, 0].item()


# (z0, z1, σ_t, emission) of each medium: partly overlapping, one inside another, the same span, three
LAYOUTS = {
    "partial": [(0.0, 2.0, 1.0, 1.0), (1.0, 3.0, 1.0, 0.0)],
    "nested": [(0.0, 3.0, 0.5, 0.0), (1.0, 2.0, 4.0, 2.0)],
    "same span": [(0.0, 2.0, 1.5, 0.5), (0.0, 2.0, 0.5, 1.0)],
    "three": [(0.0, 2.0, 1.0, 1.0), (1.0, 3.0, 2.0, 0.0), (0.5, 2.5, 0.25, 3.0)],
}


def emissive(layout):
    return [slab_box(z0, z1, sigma, emission=[e, e, e]) for z0, z1, sigma, e in layout]


# the scattering media's albedo: with an unshadowed sun their source is σ_t·albedo·p·E, constant
ALBEDO = 0.6


@pytest.mark.parametrize("closed_form", [True, False])
@pytest.mark.parametrize("name", list(LAYOUTS))
@pytest.mark.parametrize("scattering", [False, True])
def test_overlapping_media_match_the_piecewise_closed_form(name, closed_form, scattering, one_thread):
    layout = LAYOUTS[name]
    albedo = ALBEDO if scattering else 0.0
    radiance, trans, distance, shares = piecewise(
        [(z0, z1, sigma, e + sigma * albedo * ISOTROPIC * SUN["intensity"]) for z0, z1, sigma, e in layout])
    for order in itertools.permutations(range(len(layout))):
        vols = [{**v, "albedo": albedo} for v in emissive([layout[i] for i in order])]
        # frostbite is exact on constant pieces: the march matches to rounding, however few its steps
        out = tv.render(axis_scene(vols, lights=[SUN] if scattering else [],
                                   march={"closed_form": closed_form, "steps": 8}), dtype=torch.float64,
                        aovs=["alpha_volumes"])
        assert out.stats["plan"]["joint"] == [f"volume{i}" for i in range(len(layout))]
        assert ("media.closed_form" in out.stats["passes"]) == closed_form
        assert_close(out.radiance[0, :, 0, 0], radiance, atol=1e-9, what=f"{name} {order}: radiance")
        assert_close(out.alpha[0, 0, 0, 0], 1.0 - trans, atol=1e-9, what=f"{name} {order}: alpha")
        # a march weights each step at its midpoint: its depth is first order in the step
        assert_close(out.depth[0, 0, 0, 0], distance, atol=1e-6 if closed_form else 2e-2,
                     what=f"{name} {order}: expected depth")
        expected = torch.tensor([shares[i] for i in order], dtype=torch.float64)
        assert_close(out.aovs["alpha_volumes"][0, :, 0, 0].double(), expected, atol=1e-6,
                     what=f"{name} {order}: alpha shares")


@pytest.mark.parametrize("closed_form", [True, False])
def test_the_median_depth_is_where_the_whole_ray_crosses_one_half(closed_form, one_thread):
    # two boxes of transmittance 0.6 each: neither alone takes a ray below 0.5, the two do, in
    # the second one at 0.6·e^{−σx} = 0.5 (the pieces' own medians once made this label 0)
    sigma = -math.log(0.6)
    for vols in ([slab_box(0, 1, sigma), slab_box(1.5, 2.5, sigma)], [slab_box(1.5, 2.5, sigma), slab_box(0, 1, sigma)]):
        out = tv.render(axis_scene(vols, march={"closed_form": closed_form, "steps": 8}), dtype=torch.float64)
        assert_close(out.aovs["depth_median"][0, 0, 0, 0], 6.5 + math.log(0.6 / 0.5) / sigma, atol=1e-9,
                     what="median depth behind a first medium")
        assert_close(out.alpha[0, 0, 0, 0], 1.0 - 0.36, atol=1e-9, what="alpha")


def test_the_issue_case_is_no_longer_nine_percent_too_bright(one_thread):
    # an emissive box (σ 1, emission 1, z 0..2) in an absorbing box (σ 1, z 1..3): (1 − e⁻¹) + e⁻¹·½(1 − e⁻²)
    exact = (1.0 - math.exp(-1.0)) + math.exp(-1.0) * 0.5 * (1.0 - math.exp(-2.0))
    for vols in ([slab_box(0, 2, 1.0, emission=[1.0] * 3), slab_box(1, 3, 1.0)],
                 [slab_box(1, 3, 1.0), slab_box(0, 2, 1.0, emission=[1.0] * 3)]):
        out = tv.render(axis_scene(vols), dtype=torch.float64)
        assert_close(out.radiance[0, 0, 0, 0], exact, atol=1e-4, what="emissive box in an absorbing box")
    assert abs(exact - 0.7912) < 1e-4


@pytest.mark.parametrize("order", [(0, 1), (1, 0)])
def test_a_scattering_cloud_nested_in_absorbing_fog(order, one_thread):
    # unshadowed sun: the cloud's source σ_s·p·E is constant; only the fog in front dims it
    fog, cloud = (-1.0, 4.0, 0.3), (1.0, 2.0, 2.0)
    source = cloud[2] * 0.9 * ISOTROPIC * SUN["intensity"]
    radiance, trans, _, _ = piecewise([(*fog, 0.0), (*cloud, source)])
    vols = [slab_box(*fog), slab_box(*cloud, albedo=0.9)]
    out = tv.render(axis_scene([vols[i] for i in order], lights=[SUN]), dtype=torch.float64)
    assert_close(out.radiance[0, :, 0, 0], radiance, atol=1e-9, what="cloud in fog: radiance")
    # the old composite took the cloud's light behind the whole fog: e^{-0.3·5} instead of e^{-0.3·2}
    assert radiance > 1.5 * radiance * math.exp(-0.3 * 3.0)


def test_a_shadow_through_a_second_medium_is_its_transmittance(one_thread):
    # the sun (+y) reaches the lit slab through an absorbing slab above it: σ_s p E e^{-τ_above}
    sun = {**SUN, "shadow": {"steps": 4}}
    lit = {"bounds": {"box": {"min": [-2.0, -0.5, 0.0], "max": [2.0, 0.5, 1.0]}}, "density": {"constant": 1.0},
           "sigma_t": 1e-6, "albedo": 1.0}
    above = {"bounds": {"box": {"min": [-2.0, 0.5, -2.0], "max": [2.0, 1.3, 3.0]}}, "density": {"constant": 1.0},
             "sigma_t": 2.0, "albedo": 0.0}
    out = tv.render(axis_scene([lit, above], lights=[sun]), dtype=torch.float64)
    # the thin lit slab: in-scatter σ_s p E T_own e^{-2·0.8} over its unit chord (its own T ≈ 1)
    expected = 1e-6 * ISOTROPIC * SUN["intensity"] * math.exp(-2.0 * 0.8)
    assert_close(out.radiance[0, 0, 0, 0] / expected, 1.0, atol=1e-5, what="shadowed in-scatter / closed form")


@pytest.mark.parametrize("density", [{"constant": 1.0},
                                     {"fbm": {"octaves": 3, "frequency": 1.5, "seed": 3, "bias": 0.2}}])
def test_a_medium_split_into_two_identical_halves_renders_as_the_whole(density, one_thread):
    sun = {**SUN, "direction": [0.3, 0.8, -0.5], "shadow": {"steps": 6}} if "constant" in density else SUN
    whole = {"bounds": {"sphere": {"center": [0.0, 0.0, 0.0], "radius": 1.0}}, "density": density,
             "sigma_t": 3.0, "albedo": 0.8, "emission": [0.2, 0.1, 0.0]}
    half = {**whole, "sigma_t": 1.5, "emission": [0.1, 0.05, 0.0]}
    s = {"image": {"width": 16, "height": 12}, "lights": [sun], "march": {"steps": 12, "closed_form": False},
         "camera": {"eye": [0.0, 0.5, -3.5], "target": [0.0, 0.0, 0.0], "fov_y": 45.0}}
    one = tv.render({**s, "volumes": [whole]}, dtype=torch.float64)
    two = tv.render({**s, "volumes": [half, half]}, dtype=torch.float64)
    assert "media.march" in two.stats["passes"]
    assert_close(two.radiance, one.radiance, atol=1e-9, what="two halves − the whole: radiance")
    assert_close(two.alpha, one.alpha, atol=1e-9, what="two halves − the whole: alpha")
    assert_close(two.depth, one.depth, atol=1e-7, what="two halves − the whole: depth")


def test_the_tolerance_march_and_empty_space_skipping_work_across_pieces(one_thread):
    # a grid of constant 1 (skippable: its occupied span cuts the ray) in an absorbing box, and the
    # error-controlled march: both hold the piecewise solution
    layout = LAYOUTS["partial"]
    radiance = piecewise(layout)[0]
    grid = {**emissive(layout)[0], "density": {"grid": {"data": np.ones((2, 2, 2)).tolist()}}}
    for march, marker in (({"steps": 4, "closed_form": False}, "volume0.skip"),
                          ({"tolerance": 1e-4, "closed_form": False}, "media.march")):
        out = tv.render(axis_scene([grid, emissive(layout)[1]], march=march), dtype=torch.float64)
        assert marker in out.stats["passes"]
        assert_close(out.radiance[0, 0, 0, 0], radiance, atol=1e-6, what=f"{march}: radiance")


def test_order_of_volumes_does_not_change_the_image_of_overlapping_clouds(one_thread):
    fbm = {"fbm": {"octaves": 3, "frequency": 1.2, "seed": 5, "bias": 0.1}}
    cloud = {"bounds": {"sphere": {"center": [0.0, 0.0, 0.0], "radius": 1.0}}, "density": fbm, "sigma_t": 4.0}
    fog = {"bounds": {"box": {"min": [-3.0, -1.0, -3.0], "max": [3.0, 0.2, 3.0]}},
           "density": {"exponential": {"value": 0.8, "base": -1.0, "scale_height": 0.5}}, "sigma_t": 1.0, "albedo": 0.9}
    s = {"image": {"width": 24, "height": 16}, "lights": [{**SUN, "shadow": {"steps": 4}}], "march": {"steps": 16},
         "camera": {"eye": [0.0, 0.8, -4.0], "target": [0.0, 0.0, 0.0], "fov_y": 50.0}}
    a = tv.render({**s, "volumes": [cloud, fog]}, aovs=["alpha_volumes"])
    b = tv.render({**s, "volumes": [fog, cloud]}, aovs=["alpha_volumes"])
    assert_close(b.radiance, a.radiance, atol=1e-5, what="[fog, cloud] − [cloud, fog]")
    assert_close(b.depth, a.depth, atol=1e-4, what="depth, either order")
    assert_close(b.aovs["alpha_volumes"].flip(1), a.aovs["alpha_volumes"], atol=1e-5, what="alpha shares, either order")
    assert_close(a.aovs["alpha_volumes"].sum(dim=1, keepdim=True), a.alpha, what="Σ alpha shares − alpha")


def test_overlap_batches_and_chunks_bitwise(one_thread):
    scenes = [axis_scene(emissive(LAYOUTS["three"]), width=9, height=7, march={"steps": 5, "closed_form": False}),
              axis_scene(emissive(LAYOUTS["partial"] + [(2.5, 4.0, 0.5, 2.0)]), width=9, height=7,
                         march={"steps": 5, "closed_form": False})]
    scenes[1]["volumes"][1]["sigma_t"] = 3.0  # one structure, other values
    batch = tv.render(scenes, aovs=["alpha_volumes", "instance"])
    for b, s in enumerate(scenes):
        alone = tv.render(s, aovs=["alpha_volumes", "instance"], chunk_rays=7)
        assert torch.equal(batch.radiance[b], alone.radiance[0]) and torch.equal(batch.depth[b], alone.depth[0])
        assert torch.equal(batch.aovs["alpha_volumes"][b], alone.aovs["alpha_volumes"][0])
        assert torch.equal(batch.aovs["instance"][b], alone.aovs["instance"][0])


def test_stats_name_the_joint_pass_and_count_each_medium(one_thread):
    out = tv.render(axis_scene(emissive(LAYOUTS["partial"]), march={"closed_form": False, "steps": 4}))
    assert out.stats["passes"] == ["rays", "media.march", "composite"]
    evals = out.stats["density_evals_by_volume"]
    assert set(evals) == {"volume0", "volume1"} and all(n > 0 for n in evals.values())
    assert sum(evals.values()) == out.stats["density_evals"]


def air_scene(volumes, rayleigh, *, steps=1024):
    """The axis ray 1 above the ground of a small planet (R 1000, its air 3 deep, homogeneous: scale
    heights far above it), lit by an overhead sun of 3: the air is a medium of the march."""
    s = axis_scene(volumes, lights=[SUN], march={"steps": 64})
    s["camera"] = {"eye": [0.0, 1.0, -5.0], "target": [0.0, 1.0, 0.0], "up": [0.0, 1.0, 0.0], "fov_y": 10.0}
    s["atmosphere"] = {"planet_radius": 1000.0, "atmosphere_height": 3.0, "rayleigh": list(rayleigh), "mie": 0.0,
                       "rayleigh_height": 1e12, "mie_height": 1e12, "steps": steps, "light_steps": 1}
    return s


def air_quadrature(rayleigh, box, n=400_000, *, reddened=True):
    """The axis ray of `air_scene` by the midpoint rule (float64): Rayleigh air of coefficients
    `rayleigh` everywhere in the shell, the sun through it to each point (its path to the shell's
    top: exact for homogeneous air), and `box` = (z0, z1, σ_t, albedo, emission) in it; not
    `reddened`: the sun reaches the box as it left the sun (what the old post pass did)."""
    r, top, eye_z = 1000.0, 1003.0, -5.0
    length = math.sqrt(top**2 - (r + 1.0) ** 2) - eye_z  # where the level ray leaves the shell
    t = (np.arange(n) + 0.5) * (length / n)
    z = eye_z + t
    beta = np.asarray(rayleigh)[:, None]
    up = np.sqrt(top**2 - z**2) - (r + 1.0)  # from the ray's point straight up to the top
    sun = 3.0 * np.exp(-beta * up)  # [3, n]
    rayleigh_phase = 3.0 / (16.0 * math.pi) * (1.0 + 0.0**2)  # the sun overhead: θ = 90°
    inside = (z >= box[0]) & (z <= box[1])
    sigma = beta + box[2] * inside
    source = beta * rayleigh_phase * sun + inside * (box[2] * box[3] * ISOTROPIC * (sun if reddened else 3.0) + box[4])
    dt = length / n
    tau = np.cumsum(sigma * dt, axis=1) - 0.5 * sigma * dt
    return (np.exp(-tau) * source * dt).sum(axis=1)


def test_a_volume_inside_the_air_and_the_sun_reddened_on_its_way(one_thread):
    rayleigh, box = (0.02, 0.05, 0.1), (0.0, 2.0, 1.0, 0.8, 0.05)
    vol = slab_box(box[0], box[1], box[2], albedo=box[3], emission=[box[4]] * 3)
    vol["bounds"]["box"]["min"][1], vol["bounds"]["box"]["max"][1] = 0.5, 1.5
    out = tv.render(air_scene([vol], rayleigh), dtype=torch.float64)
    assert out.stats["passes"] == ["rays", "atmosphere", "media.march", "composite"]
    expected = torch.from_numpy(air_quadrature(rayleigh, box))
    assert_close(out.radiance[0, :, 0, 0] / expected, torch.ones(3, dtype=torch.float64), atol=5e-5,
                 what="radiance / quadrature of the air with the box in it")
    # the test sees both: the box's share of the radiance, and the air on the sun's way to it
    clear = torch.from_numpy(air_quadrature(rayleigh, (0.0, 0.0, 0.0, 0.0, 0.0)))
    unreddened = torch.from_numpy(air_quadrature(rayleigh, box, reddened=False))
    assert (expected - clear).min() > 0.1 * clear.min()
    assert ((unreddened - expected).abs() / expected).max() > 50 * 2e-4


def test_the_terrain_is_lit_through_the_air(one_thread):
    # flat ground 0.5 under the camera, the sun overhead through 3 units of homogeneous air: its
    # direct light is e^{−β·3} of the clear air's, and the view ray's air takes e^{−β·d} more
    # (the air's own in-scatter, β·p·E·d ≈ 0.2 % of the ground here, is inside the tolerance)
    rayleigh = (0.02, 0.05, 0.1)
    s = air_scene([], rayleigh)
    s.pop("volumes")
    s["camera"] = {"eye": [0.0, 0.5, -0.5], "target": [0.0, 0.0, 0.0], "fov_y": 10.0}
    s["terrain"] = {"base": 0.0, "amplitude": 0.0, "color": [1.0, 1.0, 1.0], "ambient": [0.0, 0.0, 0.0]}
    hazy = tv.render(s, dtype=torch.float64)
    clear = tv.render({**s, "atmosphere": {**s["atmosphere"], "rayleigh": [0.0, 0.0, 0.0]}}, dtype=torch.float64)
    d = math.hypot(0.5, 0.5)  # the eye to the ground point it looks at
    expected = torch.exp(-torch.tensor(rayleigh, dtype=torch.float64) * (3.0 + d))
    assert_close(hazy.radiance[0, :, 0, 0] / clear.radiance[0, :, 0, 0], expected, atol=5e-3,
                 what="ground lit through the air / in clear air")


def test_the_error_controlled_march_holds_the_air_too(one_thread):
    # (the air alone on a piece has σ_t 0, not the −inf "no medium here" of a signed sum: found by
    # the fuzz, it made the transmittance inf and the image NaN)
    rayleigh, box = (0.02, 0.05, 0.1), (0.0, 2.0, 1.0, 0.8, 0.05)
    vol = slab_box(box[0], box[1], box[2], albedo=box[3], emission=[box[4]] * 3)
    vol["bounds"]["box"]["min"][1], vol["bounds"]["box"]["max"][1] = 0.5, 1.5
    s = air_scene([vol], rayleigh)
    s["march"] = {"tolerance": 1e-4, "closed_form": False}
    out = tv.render(s, dtype=torch.float64)
    expected = torch.from_numpy(air_quadrature(rayleigh, box))
    assert_close(out.radiance[0, :, 0, 0] / expected, torch.ones(3, dtype=torch.float64), atol=1e-3,
                 what="radiance / quadrature, error-controlled march")


@settings(max_examples=40, deadline=None)
@given(m=st.integers(1, 10), n=st.integers(1, 40), seed=st.integers(0, 2**16))
def test_a_rays_cuts_are_sorted_as_torch_sorts_them(m, n, seed):
    """`sorted_rows` (a min/max network for up to 8 cuts, torch.sort beyond) gives the values of
    `sort(dim=0)`: ties, infinities and zeros of either sign included."""
    from torchvol.volume.joint import sorted_rows

    g = torch.Generator().manual_seed(seed)
    x = torch.randint(-3, 4, (m, n), generator=g).float()
    x[torch.rand(m, n, generator=g) < 0.2] = math.inf
    x[torch.rand(m, n, generator=g) < 0.1] = -0.0
    got, want = sorted_rows(x), x.sort(dim=0).values
    assert torch.equal(got, want), f"largest error {(got - want).abs().nan_to_num().max()} with {m} cuts"
