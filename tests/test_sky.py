"""Sky kinds: the template's gradient with halo/flare, and the Rayleigh + Mie atmosphere."""

import pytest
import torch
from conftest import assert_close

import torchvol as tv
from torchvol.light import sky


def test_gradient_sky_and_glow_are_the_templates_formulas():
    d = torch.nn.functional.normalize(torch.tensor([[0.3, 0.5, 0.8], [-0.7, 0.0, -0.7]], dtype=torch.float64), dim=1)
    sun = torch.nn.functional.normalize(torch.tensor([[-0.7, 0.0, -0.7]] * 2, dtype=torch.float64), dim=1)
    horizon = torch.tensor([[0.675, 0.785, 0.825]] * 2, dtype=torch.float64)
    slope = torch.tensor([[0.2, 0.1, 0.2]] * 2, dtype=torch.float64)
    expected = torch.tensor([0.6, 0.71, 0.75], dtype=torch.float64) - d[:, 1:2] * 0.2 * torch.tensor([1.0, 0.5, 1.0]) + 0.075
    assert_close(sky.gradient_sky(d, horizon, slope), expected, what="gradient")
    glow = sky.sun_glow(d, sun, torch.tensor([[0.2, 0.12, 0.02]] * 2, dtype=torch.float64), torch.tensor([8.0, 8.0], dtype=torch.float64))
    assert_close(glow[1], torch.tensor([0.2, 0.12, 0.02], dtype=torch.float64), what="halo towards the sun")
    assert glow[0].abs().max() == 0  # facing away: clamp(dot, 0, 1) = 0


def atmosphere_scene(sun, target=(0.0, 0.3, 1.0)):
    return {"image": {"width": 24, "height": 12}, "camera": {"eye": [0, 0, 0], "target": list(target), "fov_y": 90},
            "sky": {"kind": "atmosphere", "atmosphere": {"steps": 8, "light_steps": 4}},
            "lights": [{"direction": list(sun)}]}


def test_atmosphere_is_blue_by_day_red_at_sunset_black_below_the_horizon():
    day = tv.render(atmosphere_scene((0.0, 1.0, 0.3), target=(0.0, 1.0, 0.01)))
    zenith = day.radiance[0, :, :6].mean(dim=(1, 2))
    assert zenith[2] > zenith[1] > zenith[0] > 0, f"zenith {zenith.tolist()} is not blue"
    dusk = tv.render(atmosphere_scene((0.0, 0.03, 1.0), target=(0.0, 0.05, 1.0)))
    horizon = dusk.radiance[0, :, 5:6, 10:14].mean(dim=(1, 2))
    assert horizon[0] > horizon[2], f"horizon under a setting sun {horizon.tolist()} is not red"
    ground = tv.render(atmosphere_scene((0.0, 1.0, 0.3), target=(0.0, -1.0, 0.01)))
    # the black ground, seen through a few metres of air: only that air's faint in-scatter
    assert ground.radiance[0, :, -3:].abs().max() < 1e-3 < day.radiance[0, :, :3].min()
    assert all(torch.isfinite(o.radiance).all() for o in (day, dusk, ground))


def test_atmosphere_needs_a_sun():
    scene = atmosphere_scene((0, 1, 0))
    scene["lights"] = []
    with pytest.raises(ValueError, match="atmosphere"):
        tv.load_scene(scene)


@pytest.mark.parametrize("kind", ["constant", "gradient"])
def test_the_sky_kernel_is_the_eager_sky(kind):
    """Where a render runs kernels a constant or gradient sky and its halo are one Dr.Jit kernel
    (`sky.sky_kernel`): the sky bitwise eager's, the halo within float rounding (its power Dr.Jit's
    exp and log), every direction, two scenes of different skies; the plan says so."""
    from torchvol.runtime.compilation import drjit_available

    if not drjit_available():
        pytest.skip("Dr.Jit's LLVM backend is not available here")
    skies = [{"kind": kind, **({"radiance": [0.2, 0.4, 0.9]} if kind == "constant" else {"horizon": [0.9, 0.6, 0.3], "slope": [-0.5, 0.0, 0.6]}),
              "halo": {"color": [1.0, 0.8, 0.5], "power": 8.0}},
             {"kind": kind, "halo": {"color": [0.3, 0.3, 0.3], "power": 300.0}}]
    scenes = [tv.load_scene({"image": {"width": 37, "height": 23}, "camera": {"fov_y": 170.0}, "sky": sky,
                             "lights": [{"kind": "sun", "direction": [0.3, 0.5 + 0.3 * i, 0.2]}]}) for i, sky in enumerate(skies)]
    fast, slow = tv.render(scenes), tv.render(scenes, compile="off")
    assert fast.stats["plan"]["sky"] == "drjit" and slow.stats["plan"]["sky"] == "eager"
    err = (fast.radiance - slow.radiance).abs()
    assert err.max() <= 1e-6 * slow.radiance.abs().max(), f"largest error {err.max():.3g}"
    no_halo = [tv.load_scene({**s.model_dump(), "sky": {**s.model_dump()["sky"], "halo": None}}) for s in scenes]
    assert torch.equal(tv.render(no_halo).radiance, tv.render(no_halo, compile="off").radiance), "the sky alone is bitwise"
