"""shading = "surface" (the seeds' variant 5, the fur ball): density-gradient normals, half-Lambert
diffuse and Blinn-Phong specular, against the seed's GLSL (furNormal and its lighting lines) run on
llvmpipe and against closed forms; the fur density; the plan and the preset."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import torchvol as tv
from tests.conftest import assert_close
from torchvol.measure.glsl import gl_context, run_fragment, shadertoy_source
from torchvol.renderer.plan import make_plan
from torchvol.volume.surface_look import density_normal, surface_light

W, H = 24, 16
EPS = 0.01
SHININESS = 50.0
LIGHT = (0.2, 0.3, -1.0)

# a smooth density with no symmetry, polynomial so GLSL and torch evaluate it alike
GLSL_DENSITY = "float sampleDensity(vec3 p) { return 1.0 - dot(p, p) + 0.5 * p.x * p.y * p.z + 0.3 * p.x * p.x * p.y; }"


def _surface_light(normal, to_light, to_eye, shininess):
    """`surface_light` (lanes) of rows [n, 3] -> (diffuse [n], specular [n])."""
    return surface_light(normal.unbind(1), to_light.unbind(1), to_eye.unbind(1), shininess)


def density(p, s=None, lod=None):
    x, y, z = p.unbind(1)
    return 1.0 - (p * p).sum(1) + 0.5 * x * y * z + 0.3 * x * x * y


# the seed's furNormal (forward differences, as written) and a central-difference variant; the
# seed's lighting lines with V = −rd and H = normalize(L + V)
BODY = GLSL_DENSITY + """
uniform int uMode;
uniform vec3 uLight;
vec3 furNormal(vec3 pos, float density) {
    float eps = EPS_VALUE;
    vec3 n;
    n.x = sampleDensity(pos + vec3(eps, 0, 0)) - density;
    n.y = sampleDensity(pos + vec3(0, eps, 0)) - density;
    n.z = sampleDensity(pos + vec3(0, 0, eps)) - density;
    return normalize(n);
}
vec3 furNormalCentral(vec3 pos) {
    float eps = EPS_VALUE;
    return normalize(vec3(sampleDensity(pos + vec3(eps, 0, 0)) - sampleDensity(pos - vec3(eps, 0, 0)),
                          sampleDensity(pos + vec3(0, eps, 0)) - sampleDensity(pos - vec3(0, eps, 0)),
                          sampleDensity(pos + vec3(0, 0, eps)) - sampleDensity(pos - vec3(0, 0, eps))));
}
void mainImage(out vec4 o, in vec2 fc) {
    vec3 pos = vec3(fc.x / 24.0 - 0.5, fc.y / 16.0 - 0.5, -0.1 - 0.01 * fc.x);
    vec3 rd = normalize(vec3(fc.x / 24.0 - 0.5, fc.y / 16.0 - 0.5, 1.0));
    float density = sampleDensity(pos);
    vec3 N = uMode == 1 ? -furNormalCentral(pos) : -furNormal(pos, density);
    vec3 L = normalize(uLight);
    vec3 H = normalize(L - rd);
    float diff = max(0.0, dot(N, L) * 0.5 + 0.5);
    float spec = pow(max(0.0, dot(N, H)), SHININESS_VALUE);
    o = uMode == 2 ? vec4(diff, spec, density, 0.0) : vec4(N, 0.0);
}
""".replace("EPS_VALUE", repr(EPS)).replace("SHININESS_VALUE", repr(SHININESS))


def torch_inputs():
    """The shader's pos and rd per pixel, [H*W, 3] float32, row 0 the top (as read back)."""
    j, i = torch.meshgrid(torch.arange(H - 1, -1, -1), torch.arange(W), indexing="ij")
    fx, fy = (i.reshape(-1) + 0.5).float(), (j.reshape(-1) + 0.5).float()
    pos = torch.stack([fx / 24.0 - 0.5, fy / 16.0 - 0.5, -0.1 - 0.01 * fx], dim=1)
    rd = torch.nn.functional.normalize(torch.stack([fx / 24.0 - 0.5, fy / 16.0 - 0.5, torch.ones_like(fx)], dim=1), dim=1)
    return pos, rd


@pytest.mark.gl
@pytest.mark.skipif(gl_context() is None, reason="no OpenGL (moderngl/EGL) context")
@pytest.mark.parametrize("mode,gradient", [(0, "forward"), (1, "central")])
def test_fur_normal_and_lighting_match_the_seed_glsl(mode, gradient):
    pos, rd = torch_inputs()
    n = pos.shape[0]
    eps = torch.full((n,), EPS)
    normal = density_normal(density, pos, torch.zeros(n, dtype=torch.long), density(pos), eps, gradient=gradient)
    gl = torch.from_numpy(run_fragment(shadertoy_source(BODY), W, H, uniforms={"uMode": mode, "uLight": LIGHT}))
    gl = gl.reshape(-1, 4)
    # float32 differences of nearby densities (eps = 0.01): the normal carries ~1e-7 / 1e-2 error
    assert_close(normal, gl[:, :3], atol=2e-4, what=f"{gradient} normal")
    print(f"{gradient}: max |normal| {float((normal - gl[:, :3]).abs().max()):.2e}")
    light = torch.nn.functional.normalize(torch.tensor([LIGHT]), dim=1).expand(n, 3)
    diff, spec = _surface_light(normal if mode == 0 else gl[:, :3], light, -rd, torch.full((n,), SHININESS))
    if mode == 0:  # the lighting on the seed's own normal
        lit = torch.from_numpy(run_fragment(shadertoy_source(BODY), W, H, uniforms={"uMode": 2, "uLight": LIGHT})).reshape(-1, 4)
        assert_close(density(pos), lit[:, 2], what="density")
        assert_close(diff, lit[:, 0], atol=2e-4, what="half-Lambert")
        assert_close(spec, lit[:, 1], atol=2e-3, what="Blinn-Phong")  # x^50 amplifies the normal's error 50-fold
        assert spec.max() > 0.5 and (spec < 0.01).any()  # the highlight and its falloff are in the grid
        print(f"max |diff| {float((diff - lit[:, 0]).abs().max()):.2e}, max |spec| {float((spec - lit[:, 1]).abs().max()):.2e}")


def test_normal_of_a_radial_density_points_outwards():
    p = torch.nn.functional.normalize(torch.randn(64, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1)), dim=1) * 0.7
    radial = lambda q, s=None, lod=None: 1.0 - q.norm(dim=1)
    s, eps = torch.zeros(64, dtype=torch.long), torch.full((64,), 1e-4, dtype=torch.float64)
    for gradient in ("central", "forward"):
        n = density_normal(radial, p, s, radial(p), eps, gradient=gradient)
        assert_close(n, p / 0.7, atol=1e-4 if gradient == "forward" else 1e-7, what=gradient)  # O(eps), O(eps²)


def test_lighting_closed_forms():
    n = torch.tensor([[0.0, 1.0, 0.0]] * 4, dtype=torch.float64)
    to_light = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    to_eye = torch.tensor([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
    diff, spec = _surface_light(n, to_light, to_eye, torch.full((4,), 8.0, dtype=torch.float64))
    assert_close(diff, torch.tensor([1.0, 0.5, 0.0, 0.5], dtype=torch.float64))  # half-Lambert: the terminator at 0.5
    # H = N: 1; light and eye opposite (H the zero vector normalised): 0; H at 45°: cos⁸ 45° = 1/16
    assert_close(spec, torch.tensor([1.0, 0.0, 0.0, 1.0 / 16.0], dtype=torch.float64))


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3), st.floats(1e-6, 1.0), st.floats(1e-3, 1e4))
def test_flat_or_extreme_inputs_stay_finite(point, eps, shininess):
    p = torch.tensor([point, point], dtype=torch.float32)
    s = torch.zeros(2, dtype=torch.long)
    flat = lambda q, s=None, lod=None: torch.full_like(q[:, 0], 0.5)
    for field in (flat, density):
        normal = density_normal(field, p, s, field(p), torch.full((2,), eps), gradient="central")
        assert normal.isfinite().all()
        light = torch.tensor([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
        diff, spec = _surface_light(normal, light, -light, torch.full((2,), shininess))
        assert diff.isfinite().all() and spec.isfinite().all() and (diff >= 0).all() and (spec >= 0).all()


def test_fur_density_core_strands_and_tips():
    scene = tv.load_scene({"volumes": [{"bounds": {"sphere": {"radius": 1.0}}, "density": {"fur": {"radius": 0.5, "length": 0.4}}}]})
    from torchvol.fields import DENSITIES
    from torchvol.schema.batch import stack

    params = stack([scene]).volumes[0].density.value
    field = DENSITIES["fur"].fn(params, torch.zeros(1))
    dirs = torch.nn.functional.normalize(torch.randn(2000, 3, generator=torch.Generator().manual_seed(0)), dim=1)
    s = torch.zeros(2000, dtype=torch.long)
    assert (field(dirs * 0.05, s) == 1.0).all()  # deep in the core (core = (radius − r) / length ≥ 1)
    assert (field(dirs * 0.91, s) < 0.05).all()  # the tips taper out
    shell = field(dirs * 0.6, s)  # between the strands: empty; on them: dense
    assert 0.01 < (shell > 0).float().mean() < 0.5 and shell.max() > 0.3
    # radial strands: the density along a ray from the centre falls monotonically
    radii = torch.linspace(0.5, 0.95, 10)
    along = torch.stack([field(dirs * r, s) for r in radii])
    assert (along[1:] <= along[:-1] + 1e-6).all()


def fur_ball(**keys):
    return tv.load_scene(tv.preset("fur-ball", width=12, height=10), {"march.step_size": 0.05, **keys})


def test_plan_and_passes_show_only_the_march():
    scene = fur_ball(**{"lights[0].shadow": {"steps": 4}})  # shadows do not apply to the surface look
    plan = make_plan(scene)
    assert plan.volumes[0].shading == "surface" and plan.volumes[0].strategy == "march"
    assert all(li.name is None and li.shadow is None for li in plan.volumes[0].lights)
    out = tv.render(scene)
    assert out.stats["passes"] == ["rays", "sky", "volume0.march", "composite"] == out.stats["plan"]["passes"]
    assert out.image.isfinite().all() and out.alpha.max() > 0.9


def test_specular_and_shininess_change_the_image_where_lit():
    base = tv.render(fur_ball()).radiance
    dull = tv.render(fur_ball(**{"volumes[0].surface.specular": [0.0, 0.0, 0.0]})).radiance
    sharper = tv.render(fur_ball(**{"volumes[0].surface.shininess": 500.0})).radiance
    assert (base >= dull - 1e-6).all() and (base - dull).max() > 0.01
    assert (base >= sharper - 1e-6).all()


@pytest.mark.parametrize("size", [(1, 1), (7, 3), (13, 11)])
def test_odd_sizes_are_finite(size):
    out = tv.render(tv.load_scene(tv.preset("fur-ball", width=size[0], height=size[1]), {"march.step_size": 0.05}))
    assert out.image.shape == (1, 3, size[1], size[0]) and out.image.isfinite().all() and out.depth.isfinite().all()


def test_bad_surface_values_are_refused():
    with pytest.raises(ValueError, match=r"volumes\[0\]\.surface\.shininess"):
        tv.load_scene(tv.preset("fur-ball"), {"volumes[0].surface.shininess": 0.0})
    with pytest.raises(ValueError, match=r"volumes\[0\]\.surface\.gradient"):
        tv.load_scene(tv.preset("fur-ball"), {"volumes[0].surface.gradient": "backward"})
    with pytest.raises(ValueError, match=r"volumes\[0\]\.density\.fur\.thickness"):
        tv.load_scene(tv.preset("fur-ball"), {"volumes[0].density.fur.thickness": -1.0})
    assert math.isfinite(tv.load_scene(tv.preset("fur-ball")).volumes[0].surface.epsilon)
    assert np.isfinite(tv.load_scene(tv.preset("fur-ball")).volumes[0].density.value.radius)


def test_rows_shade_alike_in_any_batch():
    """Normals and lighting round the same for a point alone or in a batch (bitwise batches)."""
    g = torch.Generator().manual_seed(3)
    p, light, eye = (torch.nn.functional.normalize(torch.randn(200, 3, generator=g), dim=1) * 0.6 for _ in range(3))
    s, eps, shine = torch.zeros(200, dtype=torch.long), torch.full((200,), 0.01), torch.full((200,), 37.0)

    def shade(i):
        n = density_normal(density, p[i], s[i], density(p[i]), eps[i], gradient="central")
        return torch.cat([n, torch.stack(_surface_light(n, light[i] / 0.6, eye[i] / 0.6, shine[i]), dim=1)], dim=1)

    whole = shade(slice(None))
    assert torch.equal(whole, torch.cat([shade(slice(i, i + 1)) for i in range(200)]))


def test_fur_ball_recipe_samples_render_as_one_batch(one_thread):
    from pathlib import Path

    recipe = tv.Recipe.load(Path(__file__).resolve().parents[2] / "datasets" / "fur-ball.toml",
                            {"image.width": 10, "image.height": 8, "march.step_size": 0.05, "march.dither_scale": 0.05})
    scenes = [recipe.sample(i, seed=0) for i in range(3)]
    assert len({s.volumes[0].surface.shininess for s in scenes}) == 3
    out = tv.render(scenes, seed=[1, 2, 3])
    assert out.image.isfinite().all() and (out.alpha.amax(dim=(1, 2, 3)) > 0.5).all()
    assert torch.equal(out.radiance[1:2], tv.render(scenes[1], seed=2).radiance)
