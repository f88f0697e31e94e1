"""The `template-clouds` preset against seed 002's template run by a real GLSL implementation
(Mesa llvmpipe through moderngl/EGL): ≥ 99% of pixels within 2/255, mean difference < 0.5/255."""

from pathlib import Path

import numpy as np
import pytest

import torchvol as tv
from torchvol.measure.glsl import gl_context, run_fragment, shadertoy_source
from torchvol.noise import lattice as noise

pytestmark = [
    pytest.mark.gl,
    pytest.mark.skipif(gl_context() is None, reason="no GL context (moderngl/EGL) on this machine"),
]

TEMPLATE = shadertoy_source((Path(tv.__file__).parent / "measure" / "template_clouds.glsl").read_text())


def glsl_template(width, height, time, mouse, texture):
    uniforms = dict(iResolution=(width, height, 1.0), iTime=time, iMouse=(mouse[0], mouse[1], 0.0, 0.0))
    return run_fragment(TEMPLATE, width, height, uniforms=uniforms, textures={"iChannel0": texture}, float_output=False)[..., :3]


@pytest.mark.parametrize(
    "width,height,time,mouse,texture_seed",
    [(64, 36, 0.0, (0.0, 0.0), 0), (80, 60, 3.7, (40.0, 20.0), 1), (48, 64, 11.0, (30.0, 50.0), 2)],
)
def test_template_matches_llvmpipe(width, height, time, mouse, texture_seed):
    texture = noise.default_noise_texture(texture_seed).numpy()
    expected = glsl_template(width, height, time, mouse, texture)
    scene = tv.preset("template-clouds", width=width, height=height, time=time, mouse=mouse, noise_texture=texture)
    ours = tv.render(scene).image[0].permute(1, 2, 0).numpy()
    ours = np.round(ours * 255) / 255  # what an RGBA8 framebuffer stores
    diff = np.abs(ours - expected).max(axis=2) * 255
    within = np.mean(diff <= 2.0 + 1e-3)
    mean = np.abs(ours - expected).mean() * 255
    worst = np.unravel_index(np.argmax(diff), diff.shape)
    assert within >= 0.99 and mean < 0.5, (
        f"{within:.2%} of pixels within 2/255, mean {mean:.3f}/255; worst {diff[worst]:.0f}/255 at (row, col) {worst}"
    )


def test_default_texture_is_the_seeded_one():
    """The preset's default texture is default_noise_texture(0): same image either way."""
    a = tv.render(tv.preset("template-clouds", width=24, height=16)).image
    b = tv.render(tv.preset("template-clouds", width=24, height=16, noise_texture=noise.default_noise_texture(0).numpy())).image
    assert (a == b).all()
