"""Effects cost nothing when absent: the plan (stats["passes"]) and the work done (density_evals)
of a scene with and without each optional term."""

from __future__ import annotations

import copy

import pytest
import torch

import torchvol as tv
from torchvol.renderer.plan import make_plan


def base(**march):
    s = {
        "image": {"width": 10, "height": 8},
        "camera": {"eye": [0.0, 0.5, -3.0], "target": [0.0, 0.0, 0.0], "fov_y": 40.0},
        "volumes": [{"bounds": {"box": {"min": [-0.6, -0.6, -0.6], "max": [0.6, 0.6, 0.6]}},
                     "density": {"fbm": {"octaves": 2, "frequency": 2.0, "bias": 0.5}}, "sigma_t": 3.0, "albedo": 0.9}],
        "march": {"quality": "draft", **march},
    }
    return s


def with_(s, **changes):
    s = copy.deepcopy(s)
    for k, v in changes.items():
        s[k] = v
    return s


SUN = {"kind": "sun", "direction": [1.0, 1.0, -0.5], "color": [1.0, 1.0, 1.0], "intensity": 1.0}
SHADOWED = {**SUN, "shadow": {"steps": 8}}
SKY = {"kind": "constant", "radiance": [0.2, 0.3, 0.4]}


def check_stats(out):
    st = out.stats
    assert list(st["time_s"]) == st["passes"], "time_s keys must equal the passes, in order"
    assert all(v > 0 for v in st["time_s"].values()), st["time_s"]
    assert st["passes"][0] == "rays" and "composite" in st["passes"]
    assert len(set(st["passes"])) == len(st["passes"])
    return st


def test_shadow_pass_only_with_shadowed_light():
    s = base()
    plain = check_stats(tv.render(with_(s, lights=[SUN])))
    shadowed = check_stats(tv.render(with_(s, lights=[SHADOWED])))
    assert "volume0.shadow0" not in plain["passes"]
    assert "volume0.shadow0" in shadowed["passes"]
    assert plain["passes"] == [p for p in shadowed["passes"] if p != "volume0.shadow0"]
    assert plain["density_evals"] < shadowed["density_evals"]
    # the march itself is the same (same steps), only the shadow rays add work
    assert plain["march_steps"] == shadowed["march_steps"]
    # an unlit scene does no shadow work either
    unlit = check_stats(tv.render(s))
    assert unlit["density_evals"] == plain["density_evals"]
    assert not any("shadow" in p for p in unlit["passes"])


def test_second_light_shadow_indexed():
    out = tv.render(with_(base(), lights=[SUN, SHADOWED]))
    passes = check_stats(out)["passes"]
    assert "volume0.shadow1" in passes and "volume0.shadow0" not in passes


def test_sky_pass_only_with_sky():
    s = base()
    no_sky = check_stats(tv.render(s))
    sky = check_stats(tv.render(with_(s, sky=SKY)))
    assert "sky" not in no_sky["passes"] and "sky" in sky["passes"]
    assert no_sky["passes"] == [p for p in sky["passes"] if p != "sky"]
    assert sky["density_evals"] == no_sky["density_evals"]


def test_no_volumes_no_march():
    s = with_(base(), volumes=[], sky=SKY)
    out = tv.render(s)
    st = check_stats(out)
    assert not any(p.startswith("volume") for p in st["passes"])
    assert st["density_evals"] == 0
    assert st["march_steps"] == 0
    assert (out.alpha == 0).all() and (out.depth == 0).all()
    # the sky alone: radiance is the sky everywhere
    assert (out.radiance - out.radiance.new_tensor(SKY["radiance"])[None, :, None, None]).abs().max() < 1e-7


@pytest.mark.parametrize("bounds", [
    {"box": {"min": [-0.6, -0.6, -0.6], "max": [0.6, 0.6, 0.6]}},
    {"sphere": {"center": [0.0, 0.0, 0.0], "radius": 0.7}},
    {"slab": {"y_min": -0.3, "y_max": 0.2}},
])
def test_homogeneous_uses_closed_form(bounds):
    s = base()
    s["volumes"][0].update(bounds=bounds, density={"constant": 1.0})
    s["lights"] = [SUN]  # unshadowed light: still closed form
    closed = check_stats(tv.render(s))
    assert "volume0.closed_form" in closed["passes"] and "volume0.march" not in closed["passes"]
    assert closed["march_steps"] == 0
    forced = copy.deepcopy(s)
    forced["march"]["closed_form"] = False
    marched = check_stats(tv.render(forced))
    assert "volume0.march" in marched["passes"] and "volume0.closed_form" not in marched["passes"]
    n_rays = 10 * 8
    assert 0 < closed["density_evals"] <= n_rays
    assert closed["density_evals"] * 4 < marched["density_evals"], (closed, marched)
    # a shadowed light needs the march (the shadow varies along the ray)
    shadow = copy.deepcopy(s)
    shadow["lights"] = [SHADOWED]
    st = check_stats(tv.render(shadow))
    assert "volume0.march" in st["passes"] and "volume0.shadow0" in st["passes"]


def test_post_passes_only_when_not_identity():
    s = base()
    st = check_stats(tv.render(s))
    assert not any(p.startswith("post.") for p in st["passes"])
    assert "resolve" not in st["passes"]
    s2 = copy.deepcopy(s)
    s2["post"] = {"tonemap": "aces", "exposure": 1.5, "vignette": 0.3}
    passes = check_stats(tv.render(s2))["passes"]
    assert {"post.tonemap.aces", "post.exposure", "post.vignette"} <= set(passes)
    s3 = copy.deepcopy(s)
    s3["image"]["spp"] = 2
    assert "resolve" in check_stats(tv.render(s3))["passes"]


def test_plan_function_matches_render_stats():
    s = tv.load_scene(with_(base(), lights=[SHADOWED], sky=SKY))
    out = tv.render(s)
    assert make_plan(s).names() == out.stats["plan"]["passes"] == out.stats["passes"]


def test_density_evals_scale_with_steps():
    few = check_stats(tv.render(base(steps=4, dither="none")))
    many = check_stats(tv.render(base(steps=16, dither="none", min_transmittance=0.0)))
    assert 0 < few["density_evals"] < many["density_evals"]
    assert few["density_evals"] == few["march_steps"]


def test_stats_record_what_ran_with_one_name_per_volume_and_light():
    """Two volumes × two shadowed lights: four shadow passes, each with its own time; each shadow
    ray also sees the other volume, a pass of its own where some shadow ray crosses it."""
    s = base()
    s["volumes"].append({**copy.deepcopy(s["volumes"][0]), "bounds": {"sphere": {"center": [0.3, 0.2, 0.0], "radius": 0.5}}})
    s["lights"] = [SHADOWED, {**SHADOWED, "direction": [-1.0, 0.5, 0.2]}]
    st = check_stats(tv.render(s))
    shadows = [p for p in st["passes"] if p.endswith((".shadow0", ".shadow1"))]
    assert shadows == ["volume0.shadow0", "volume0.shadow1", "volume1.shadow0", "volume1.shadow1"]
    cross = [p for p in st["plan"]["passes"] if ".shadow" in p and p not in shadows]
    assert cross == ["volume0.shadow0.volume1", "volume0.shadow1.volume1", "volume1.shadow0.volume0", "volume1.shadow1.volume0"]
    assert all(st["time_s"][p] > 0 for p in st["passes"]), st["time_s"]
    assert set(st["passes"]) <= set(st["plan"]["passes"])  # cross passes first run when a shadow ray first meets the other volume
    assert set(st["passes"]) >= set(cross)


def test_a_planned_pass_that_finds_nothing_to_do_is_not_reported():
    """A volume behind the camera: planned, never marched, so not in `passes`."""
    s = base()
    s["volumes"][0]["bounds"] = {"box": {"min": [-0.5, -0.5, -9.0], "max": [0.5, 0.5, -8.0]}}
    s["lights"] = [SHADOWED]
    st = tv.render(s).stats
    assert "volume0.shadow0" in st["plan"]["passes"] and "volume0.shadow0" not in st["passes"]
    assert st["density_evals"] == 0


def test_post_fog_fogs_voxel_only_scenes():
    wall = {
        "image": {"width": 8, "height": 6},
        "camera": {"eye": [0.5, 0.5, -6.0], "target": [0.5, 0.5, 0.0], "fov_y": 30.0},
        "voxels": {"occupancy": {"grid": {"data": [[[1]]]}}, "cells": {"min": [-2, -2, 0], "max": [3, 3, 1]}},
        "lights": [SUN],
    }
    clear = tv.render(wall)
    foggy = tv.render({**wall, "post": {"fog": {"color": [1.0, 0.0, 0.0], "density": 0.2}}})
    assert "post.fog" in foggy.stats["passes"] and "distance" in foggy.aovs
    hit = clear.depth[0, 0] > 0
    assert hit.any() and (foggy.image[0, 0][hit] > clear.image[0, 0][hit]).all()  # redder where the wall is
    assert torch.equal(foggy.image[0, :, ~hit], clear.image[0, :, ~hit])  # nothing hit: no fog
    with pytest.raises(ValueError, match=r"^post\.fog"):
        tv.load_scene({"post": {"fog": {}}})


def test_lod_keeps_the_fields_own_octaves():
    """LOD drops octaves from the field's own count: at a tiny scale nothing is dropped from an
    8-octave fbm (the same image as without LOD, to the bit), at a large one octaves go."""
    s = base(steps=12, dither="none")
    s["volumes"][0]["density"]["fbm"]["octaves"] = 8
    full = tv.render(s)
    near = tv.render({**s, "march": {**s["march"], "lod": {"scale": 1e-4}}})
    far = tv.render({**s, "march": {**s["march"], "lod": {"scale": 50.0}}})
    five = copy.deepcopy(s)
    five["volumes"][0]["density"]["fbm"]["octaves"] = 5
    assert torch.equal(near.alpha, full.alpha)
    assert not torch.equal(far.alpha, full.alpha)
    assert not torch.equal(tv.render(five).alpha, full.alpha)
    with pytest.raises(ValueError, match=r"^march\.lod"):  # nothing to drop: refused, not ignored
        tv.load_scene({**s, "volumes": [{"density": {"constant": 1.0}}], "march": {"lod": {"scale": 0.5}}})


def test_the_plan_records_the_sun_each_marchs_backend_the_walk_and_the_thread_policy():
    """Every decision is the plan's, made once (not per chunk) and reported in stats["plan"]."""
    import json

    from torchvol.runtime.compilation import drjit_available

    template = tv.preset("template-clouds", width=8, height=8)
    drjit = drjit_available()
    fast = make_plan(template, compile="kernels")
    assert fast.sun == 0 and fast.volumes[0].backend == ("drjit" if drjit else "eager")
    assert fast.threads == ("glue_on_one_thread" if drjit else "caller")
    wide = make_plan(template, compile="kernels", dtype=torch.float64).volumes[0]  # Dr.Jit: float32
    assert wide.backend == "eager" and wide.eager_because == "Dr.Jit renders float32 on the CPU, not float64 on cpu"
    eager = make_plan(template)
    assert eager.volumes[0].backend == "eager" and eager.threads == "caller" and eager.walk is None
    assert make_plan(tv.preset("homogeneous-box", width=8, height=8)).volumes[0].backend == "closed_form"
    # a physical medium's march is the Dr.Jit kernel but under "off", where Dr.Jit runs
    assert make_plan(tv.preset("cloud-puff", width=8, height=8), compile="kernels").volumes[0].backend == ("drjit" if drjit else "eager")
    # the voxel walks: Dr.Jit's wherever a kernel runs, else eager (the same bits)
    assert make_plan(tv.preset("voxel-fog", width=8, height=8), compile="kernels").walk == ("drjit" if drjit else "eager")
    assert make_plan(tv.preset("voxel-fog", width=8, height=8), compile="kernels", dtype=torch.float64).walk == "eager"
    assert make_plan(tv.preset("voxel-fog", width=8, height=8), compile="off").walk == "eager"
    point_first = {"image": {"width": 8, "height": 8}, "volumes": [{"density": {"constant": 1.0}}],
                   "lights": [{"kind": "point", "position": [0.0, 3.0, 0.0]}, {"kind": "sun", "direction": [0, 1, 0]}]}
    assert make_plan(tv.load_scene(point_first)).sun is None  # lights[0] is not directional: no sun
    assert make_plan(tv.load_scene({**point_first, "lights": point_first["lights"][::-1]})).sun == 0
    out = tv.render(tv.preset("cloud-puff", width=8, height=8))
    assert out.stats["plan"] == make_plan(tv.preset("cloud-puff", width=8, height=8), compile="kernels").summary()
    assert json.loads(json.dumps(out.stats["plan"])) == out.stats["plan"]
    assert set(out.stats["plan"]) == {"passes", "sun", "marches", "sky", "threads", "compile", "dtype"}  # its gradient sky a kernel too
