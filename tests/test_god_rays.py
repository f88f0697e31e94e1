"""Screen-space god rays (post.god_rays): radial samples towards the sun's projected position,
occluded by alpha, scaled by max(0, view · sun); off or with the sun behind the camera they change
nothing, to the bit."""

import math

import numpy as np
import pytest
import torch
from conftest import assert_close

import torchvol as tv
from torchvol.geometry.camera import Camera
from torchvol.post import View, god_rays, sun_on_screen
from torchvol.schema.batch import stack

SCENE = {
    "image": {"width": 15, "height": 11},
    "camera": {"eye": [0.0, 0.0, -3.0], "target": [0.0, 0.0, 0.0], "fov_y": 60.0},
    "sky": {"kind": "constant", "radiance": [0.4, 0.5, 0.7], "halo": {"color": [2.0, 1.8, 1.5], "power": 16.0}},
    "lights": [{"kind": "sun", "direction": [0.2, 0.3, 1.0], "intensity": 3.0}],
    "volumes": [{"bounds": {"sphere": {"center": [0.0, 0.0, 0.0], "radius": 0.6}}, "density": {"constant": 1.0},
                 "sigma_t": 8.0}],
    "march": {"quality": "draft", "steps": 8},
}
RAYS = {"samples": 16, "density": 0.9, "decay": 0.95, "weight": 0.1, "exposure": 1.0, "power": 4.0}


def with_rays(**changes) -> dict:
    scene = {**SCENE, "post": {"god_rays": {**RAYS, **changes}}}
    return scene


def test_off_is_not_planned_and_exposure_zero_changes_nothing(one_thread):
    off = tv.render(SCENE)
    assert "post.god_rays" not in off.stats["plan"]["passes"] and "post.god_rays" not in off.stats["passes"]
    zero = tv.render(with_rays(exposure=0.0))
    assert "post.god_rays" in zero.stats["passes"] and torch.equal(zero.image, off.image)
    on = tv.render(with_rays())
    assert (on.image >= off.image).all() and (on.image > off.image).any()


def test_the_sun_behind_the_camera_changes_nothing(one_thread):
    behind = {**SCENE, "lights": [{**SCENE["lights"][0], "direction": [0.1, 0.2, -1.0]}]}
    off = tv.render(behind)
    on = tv.render({**behind, "post": {"god_rays": RAYS}})
    assert torch.equal(on.image, off.image)


def camera(w: int, h: int) -> Camera:
    eye = torch.tensor([[0.0, 0.0, 0.0]], dtype=torch.float64)
    return Camera.look_at(eye, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64), torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64),
                          width=w, height=h, fov_y=torch.tensor([60.0], dtype=torch.float64))


def params(**changes):
    scene = tv.load_scene(with_rays(**changes))
    return stack([scene]).post.god_rays


def test_the_sun_projects_where_the_camera_sees_it():
    cam = camera(32, 20)
    xy, _, facing = sun_on_screen(cam, torch.tensor([[0.0, 0.0, 2.0]]), torch.float64)
    assert_close(xy[0], torch.tensor([15.5, 9.5], dtype=torch.float64), what="principal point")
    assert_close(facing, torch.tensor([1.0], dtype=torch.float64))
    fy = 10.0 / math.tan(math.radians(30.0))
    xy, _, facing = sun_on_screen(cam, torch.tensor([[0.0, 0.2, 1.0]], dtype=torch.float64), torch.float64)  # above: a smaller row
    assert_close(xy[0], torch.tensor([15.5, 9.5 - 0.2 * fy], dtype=torch.float64), atol=1e-9, what="sun above")
    _, _, facing = sun_on_screen(cam, torch.tensor([[0.0, 0.0, -1.0]]), torch.float64)
    assert facing.item() < 0


def test_rays_through_a_gap_are_brighter_than_behind_the_occluder():
    # the sun straight ahead (the image centre) behind an opaque disc with a slit to the right
    w = h = 33
    image = torch.ones(1, 3, h, w, dtype=torch.float64)
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64) - 16, torch.arange(w, dtype=torch.float64) - 16, indexing="ij")
    r = (xx**2 + yy**2).sqrt()
    disc = (r < 8) & ~((xx > 0) & (yy.abs() < 2.5))
    alpha = disc.to(torch.float64)[None, None]
    view = View(camera=camera(w, h), sun=torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64), alpha=alpha)
    shafts = god_rays(image, params(power=50.0, samples=32), view) - image
    right, left = shafts[0, 0, 16, 16 + 12], shafts[0, 0, 16, 16 - 12]
    assert right > 2.0 * left > 0
    # rays only add light, and stay finite
    assert torch.isfinite(shafts).all() and (shafts >= 0).all()


@pytest.mark.parametrize("size", [(1, 1), (7, 13), (13, 7), (2, 31)])
@pytest.mark.parametrize("sun", [(0.0, 0.0, 1.0), (5.0, -3.0, 1.0), (1.0, 0.0, 1e-7), (0.0, 1.0, 0.0)])
def test_finite_at_odd_sizes_and_off_screen_suns(size, sun):
    w, h = size
    image = torch.rand(1, 3, h, w, generator=torch.Generator().manual_seed(0))
    alpha = torch.rand(1, 1, h, w, generator=torch.Generator().manual_seed(1))
    view = View(camera=camera(w, h), sun=torch.tensor([sun]), alpha=alpha)
    out = god_rays(image, params(), view)
    assert torch.isfinite(out).all() and (out >= image).all()


@pytest.mark.parametrize("lights", [[], [{"kind": "point", "position": [0.0, 1.0, 0.0]}]])
def test_needs_a_sun_first(lights):
    with pytest.raises(ValueError, match=r"post\.god_rays.*lights\[0\]"):
        tv.load_scene({**with_rays(), "sky": None, "lights": lights})


def test_the_preset_shows_both_kinds_of_shaft(one_thread):
    out = tv.render(tv.preset("god-rays", width=24, height=24))
    assert {"volume0.shadow0", "post.god_rays"} <= set(out.stats["passes"]) and torch.isfinite(out.image).all()
    physical = tv.render(tv.preset("god-rays", width=24, height=24, method="physical"))
    assert "post.god_rays" not in physical.stats["passes"]
    with pytest.raises(ValueError, match="god-rays.method"):
        tv.preset("god-rays", method="both ways")


RADIAL_GLSL = """
uniform vec2 center;  // the sun in pixels: column, row from the top (pixel centres at integers)
uniform float density;
uniform float decay;
uniform float weight;
uniform int samples;

float fetch(ivec2 p) {  // texel [row, column] of the uploaded array; black outside the image
    ivec2 size = ivec2(iResolution.xy);
    if (any(lessThan(p, ivec2(0))) || p.x >= size.x || p.y >= size.y) return 0.0;
    return texelFetch(iChannel0, p, 0).r;
}

float bilinear(vec2 p) {
    vec2 f = floor(p);
    vec2 t = p - f;
    ivec2 i = ivec2(f);
    return mix(mix(fetch(i), fetch(i + ivec2(1, 0)), t.x), mix(fetch(i + ivec2(0, 1)), fetch(i + ivec2(1, 1)), t.x), t.y);
}

// GPU Gems 3, ch. 13, listing 13-7, in pixels
void mainImage(out vec4 fragColor, in vec2 fragCoord) {
    vec2 pix = vec2(fragCoord.x - 0.5, iResolution.y - 0.5 - fragCoord.y);
    vec2 delta = (pix - center) * density / float(samples);
    float color = fetch(ivec2(pix + 0.5));
    float illumination = 1.0;
    vec2 p = pix;
    for (int i = 0; i < samples; i++) {
        p -= delta;
        color += bilinear(p) * illumination * weight;
        illumination *= decay;
    }
    fragColor = vec4(color, 0.0, 0.0, 1.0);
}
"""


@pytest.mark.parametrize("center", [(9.3, 6.7), (-20.0, 30.5)])
def test_radial_blur_matches_gpu_gems_glsl_on_llvmpipe(center):
    from torchvol.measure.glsl import gl_context, run_fragment, shadertoy_source
    from torchvol.post import radial_blur

    if gl_context() is None:
        pytest.skip("no OpenGL (moderngl/EGL) context")
    w, h = 23, 17
    texels = np.random.default_rng(0).integers(0, 256, (h, w), dtype=np.uint8)
    tex = np.stack([texels] * 3 + [np.full_like(texels, 255)], axis=-1)
    uniforms = {"center": center, "density": 0.9, "decay": 0.93, "weight": 0.2, "samples": 24}
    glsl = run_fragment(shadertoy_source(RADIAL_GLSL), w, h, uniforms=uniforms, textures={"iChannel0": tex})[..., 0]
    source = torch.as_tensor(texels, dtype=torch.float64)[None, None] / 255.0
    one = lambda v: torch.tensor([v], dtype=torch.float64)
    ours = radial_blur(source, torch.tensor([center], dtype=torch.float64), samples=24, density=one(0.9),
                       decay=one(0.93), weight=one(0.2))[0, 0]
    assert_close(torch.as_tensor(glsl, dtype=torch.float64), ours, atol=2e-5, what="radial blur vs GLSL")
