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
