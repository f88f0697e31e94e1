"""Production cloudscapes: tileable noise textures, the cloud type's height profile, coverage, the
ambient gradient and the sky blend, dual-lobe HG against the seeds' GLSL, the preset; the density and the
shell's interval traced by Dr.Jit against their eager runs (the kernel's renders: test_kernel_march.py)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from conftest import assert_close
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import torchvol as tv
from torchvol.fields.cloudscape import (
    CLOUD_TYPES,
    Cloudscape,
    CloudscapeDensity,
    cloudscape_density,
    cloudscape_lanes,
    height_gradient,
)
from torchvol.light.phase import dual_henyey_greenstein
from torchvol.noise import lattice as noise
from torchvol.noise import tiles as noise_tiles
from torchvol.renderer.plan import make_plan
from torchvol.runtime.compilation import drjit_available
from torchvol.schema.batch import stack, take

F64 = torch.float64


def _points(n: int, seed: int, scale: float = 5.0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=g, dtype=F64) * 2.0 - 1.0) * scale


# ---------------------------------------------------------------------------------------------
# tileable textures


@pytest.mark.parametrize("fn", [noise.perlin_noise, noise.worley_noise])
def test_periodic_lattice_noise_tiles(fn):
    p = _points(200, 1)
    for period in (3, 8):
        for axis in range(3):
            shift = torch.zeros(3, dtype=F64)
            shift[axis] = period
            assert_close(fn(p + shift, seed=4, period=period), fn(p, seed=4, period=period), atol=1e-9, what=f"period {period}")


def test_generating_noises_tile_with_period_one():
    uvw = _points(100, 2, 1.0)
    for fn in (noise_tiles.perlin_worley, lambda x, seed: noise_tiles.worley_fbm(x, seed=seed, frequencies=(2, 4))):
        for shift in ([1.0, 0.0, 0.0], [0.0, -2.0, 0.0], [0.0, 0.0, 3.0]):
            assert_close(fn(uvw + torch.tensor(shift, dtype=F64), seed=3), fn(uvw, seed=3), atol=1e-9, what=str(shift))


@pytest.mark.parametrize("texture", [noise_tiles.base_texture(0, 16), noise_tiles.detail_texture(0, 8)])
def test_textures_tile_and_trilinear_matches_nodes(texture):
    n = texture.shape[0]
    assert texture.dtype == torch.float32 and float(texture.min()) == 0.0 and float(texture.max()) == 1.0
    nodes = noise_tiles.texture_nodes(n).to(F64)
    tex = texture.to(F64)
    # at a node, the lookup is the node's value, exactly
    assert torch.equal(noise_tiles.sample_tiled(tex, nodes), tex.reshape(-1))
    # wraps: p and p + k (any integer k per axis) read the same value
    uvw = _points(300, 5, 2.0)
    for shift in ([1.0, 0.0, 0.0], [0.0, 1.0, -1.0], [-2.0, 3.0, 1.0]):
        assert_close(noise_tiles.sample_tiled(tex, uvw + torch.tensor(shift, dtype=F64)), noise_tiles.sample_tiled(tex, uvw),
                     atol=1e-9, what=f"wrap {shift}")
    # halfway between the last node and the first (across the seam): the mean of the two
    i = torch.arange(n)
    edge = torch.stack([torch.full_like(i, n - 1), i, i], 1).to(F64) / n + torch.tensor([0.5 / n, 0.0, 0.0], dtype=F64)
    want = 0.5 * (tex[i, i, n - 1] + tex[i, i, 0])
    assert_close(noise_tiles.sample_tiled(tex, edge), want, atol=1e-12, what="seam midpoint")


def test_texture_nodes_hold_the_generating_noise():
    size = 8
    raw = noise_tiles.perlin_worley(noise_tiles.texture_nodes(size), seed=2)
    want = ((raw - raw.min()) / (raw.max() - raw.min())).reshape(size, size, size)
    assert_close(noise_tiles.base_texture(2, size), want, atol=1e-6, what="base texture nodes")
    assert noise_tiles.base_texture(2, size) is noise_tiles.base_texture(2, size)  # built once


# ---------------------------------------------------------------------------------------------
# the density


@pytest.mark.parametrize("cloud_type", [0.0, 1 / 3, 0.5, 2 / 3, 0.9, 1.0])
def test_height_gradient_ends_at_zero_and_vanishes_outside(cloud_type):
    h = torch.linspace(-0.5, 1.5, 2001, dtype=F64)
    g = height_gradient(h, torch.full_like(h, cloud_type))
    assert float(g.min()) >= 0.0 and float(g.max()) <= 1.0
    assert torch.all(g[(h <= 0.0) | (h >= 1.0)] == 0.0)
    assert float(g.max()) > 0.5  # every type has clouds somewhere in the layer


def test_height_gradient_types_are_the_table_and_blend():
    h = torch.linspace(0, 1, 101, dtype=F64)
    for k, (a, b, c, d) in enumerate(CLOUD_TYPES):
        g = height_gradient(h, torch.full_like(h, k / 3))
        t0 = ((h - a) / (b - a)).clamp(0, 1)
        t1 = ((h - c) / (d - c)).clamp(0, 1)
        assert_close(g, t0 * t0 * (3 - 2 * t0) * (1 - t1 * t1 * (3 - 2 * t1)), atol=1e-12, what=f"type {k}")
    # stratus stays low, cumulonimbus reaches the top
    assert float(height_gradient(torch.tensor([0.5], dtype=F64), torch.tensor([0.0], dtype=F64))) == 0.0
    assert float(height_gradient(torch.tensor([0.9], dtype=F64), torch.tensor([1.0], dtype=F64))) > 0.5


def _field(**keys) -> Cloudscape:
    params = stack([CloudscapeDensity(**keys)], dtype=F64)
    return Cloudscape(params, torch.zeros(1, dtype=F64))


@pytest.mark.parametrize("planet_radius", [None, 50.0])
def test_density_is_zero_outside_the_layer(planet_radius):
    field = _field(bottom=1.0, top=3.0, coverage=1.0, erosion=0.0, type=1.0, scale=4.0, planet_radius=planet_radius)
    p = _points(4000, 7, 6.0)
    s = torch.zeros(len(p), dtype=torch.long)
    h = field.height(p, s)
    d = field(p, s)
    assert torch.all(d[(h <= 0) | (h >= 1)] == 0.0) and torch.all(torch.isfinite(d))
    assert float(d.max()) > 0.5 and float(d.max()) <= 1.0
    signed = field.signed(p, s)
    assert torch.equal(signed.clamp_min(0.0), d)  # signed: the density where there is some, < 0 elsewhere


def _drjit_lanes(s: torch.Tensor):
    """What a Dr.Jit kernel hands a density's ``lanes`` inputs for points of scenes `s` [n]
    (`volume.kernel_march`), and a float32 tensor [n] or [n, C] as lanes."""
    from drjit.llvm import Float, Int32

    def floats(t):
        return Float(t.to(torch.float32).contiguous().numpy())

    def lane(t):
        return floats(t) if t.ndim == 1 else [floats(c) for c in t.unbind(1)]

    return SimpleNamespace(per_lane=lambda v: lane(take(v, s)), scene=s, floats=floats,
                           ints=lambda t: Int32(t.to(torch.int32).numpy())), lane


def _awkward_points(field: Cloudscape, n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """float32 points [N, 3] of scenes [N] of `field`'s two: in and around the layer, in it on
    both textures' nodes along x and z across several periods (u = k / size, k from −2·size to
    2·size: every seam and wrap-around), and far outside it (up to 1e6 away)."""
    g = torch.Generator().manual_seed(seed)
    near = (torch.rand(n, 3, generator=g, dtype=F64) * 2 - 1) * torch.tensor([200.0, 4.0, 200.0], dtype=F64)
    far = (torch.rand(n // 4, 3, generator=g, dtype=F64) * 2 - 1) * 10.0 ** torch.randint(2, 7, (n // 4, 3), generator=g)
    p, (offset, shift) = [near + torch.tensor([0.0, 2.0, 0.0], dtype=F64), far], (field.p.offset[0].to(F64), field.shift[0].to(F64))
    for scale, size in ((field.p.scale[0], noise_tiles.BASE_SIZE), (field.p.detail_scale[0], noise_tiles.DETAIL_SIZE)):
        k = torch.arange(-2 * size, 2 * size + 1, dtype=F64) / size
        x, z = ((k - offset[c]) * float(scale) + shift[c] for c in (0, 2))
        p.append(torch.stack([x, torch.full_like(x, 2.0), z], 1))
    p = torch.cat(p)
    s = torch.randint(0, 2, (len(p),), generator=g)
    return p.to(torch.float32), s


@pytest.mark.skipif(not drjit_available(), reason="Dr.Jit's LLVM backend is not available")
@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True)
@given(planet_radius=st.sampled_from([None, 300.0, 1000.0]), cloud_type=st.floats(0.0, 1.0),
       coverage=st.floats(0.0, 1.0), erosion=st.floats(0.0, 3.0), scale=st.floats(0.5, 20.0),
       offset=st.tuples(*[st.floats(-3.0, 3.0)] * 3), wind=st.tuples(*[st.floats(-1.0, 1.0)] * 3), seed=st.integers(0, 99))
def test_the_density_traced_by_drjit_is_the_eager_one(planet_radius, cloud_type, coverage, erosion, scale, offset, wind,
                                                      seed):
    """`cloudscape_density` traced by Dr.Jit against the eager field (the same function on torch
    columns) at random points of two scenes of two seeds, at texture seams and wrap-arounds, and
    far outside the layer. Dr.Jit's fast-math square root and fused multiply-adds round an ulp or
    two apart from torch's; the height profile's steep smoothsteps and the coverage remap (× 10)
    amplify an ulp of a planet's altitude up to ~100-fold (1.3e-5 at most over 60 draws; 5e-7
    over flat ground)."""
    keys = dict(bottom=1.0, top=3.0, planet_radius=planet_radius, type=cloud_type, coverage=coverage, erosion=erosion,
                scale=scale, detail_scale=scale / 8, offset=offset, wind=wind)
    field = Cloudscape(stack([CloudscapeDensity(seed=0, **keys), CloudscapeDensity(seed=1, **{**keys, "coverage": 1 - coverage})],
                             dtype=torch.float32), torch.full((2,), 1.5))
    p, s = _awkward_points(field, 2000, seed)
    eager = field.signed(p, s)
    to, lane = _drjit_lanes(s)
    traced = torch.from_numpy(np.array(cloudscape_density(cloudscape_lanes(field, to), lane(p))))
    assert torch.all(torch.isfinite(eager))
    assert_close(traced, eager, atol=5e-5, what="Dr.Jit against eager")


def test_coverage_grows_the_clouds_and_zero_is_empty():
    p = _points(4000, 8, 6.0)
    p[:, 1] = p[:, 1].abs() * 0.5 + 1.0  # inside the layer [1, 4]
    s = torch.zeros(len(p), dtype=torch.long)
    filled = [float((_field(bottom=1.0, top=4.0, coverage=c)(p, s) > 0).double().mean()) for c in (0.0, 0.3, 0.6, 0.9, 1.0)]
    assert filled[0] == 0.0 and all(a <= b for a, b in zip(filled, filled[1:])) and filled[-1] > 0.5


# ---------------------------------------------------------------------------------------------
# renders


# the seeds' production-cloud ambient, (39, 67, 87) · 1.5/255 below and (149, 167, 200) · 1.5/255 above
SEEDS_AMBIENT = {"radiance": [c * 1.5 / 255.0 for c in (39.0, 67.0, 87.0)],
                 "top": [c * 1.5 / 255.0 for c in (149.0, 167.0, 200.0)], "visibility": "none"}


def _scene(**volume) -> dict:
    vol = {"bounds": {"slab": {"y_min": 1.0, "y_max": 3.0}},
           "density": {"cloudscape": {"bottom": 1.0, "top": 3.0, "coverage": 0.6, "scale": 6.0, "detail_scale": 1.5}},
           "sigma_t": 4.0, "albedo": 0.9, "phase": {"dual_hg": {}}}
    vol.update(volume)
    return {"image": {"width": 12, "height": 10},
            "camera": {"eye": [0.0, 0.2, 0.0], "target": [0.0, 2.0, 6.0], "fov_y": 70.0},
            "sky": {"kind": "gradient", "horizon": [0.6, 0.7, 0.8], "slope": [0.4, 0.3, 0.0]},
            "lights": [{"kind": "sun", "direction": [0.2, 0.5, 1.0], "intensity": 3.0, "shadow": {"steps": 3}}],
            "volumes": [vol],
            "march": {"quality": "draft", "steps": 12, "max_distance": 30.0}}


def test_coverage_zero_renders_the_sky():
    scene = _scene(density={"cloudscape": {"bottom": 1.0, "top": 3.0, "coverage": 0.0}}, sky_blend=0.01, ambient=SEEDS_AMBIENT)
    out = tv.render(tv.load_scene(scene))
    sky = tv.render(tv.load_scene({**scene, "volumes": []}))
    assert torch.equal(out.radiance, sky.radiance) and torch.all(out.alpha == 0)


def test_sky_blend_fades_the_clouds_into_the_sky():
    near = tv.render(tv.load_scene(_scene()), dtype=F64)
    sky = tv.render(tv.load_scene({**_scene(), "volumes": []}), dtype=F64)
    assert float(near.alpha.max()) > 0.5
    # a blend that is complete at any distance: the medium shows the sky it hides, the image is the sky
    gone = tv.render(tv.load_scene(_scene(sky_blend=1e6)), dtype=F64)
    assert_close(gone.radiance, sky.radiance, atol=1e-9, what="fully blended")
    assert torch.equal(gone.alpha, near.alpha)  # opacity and depth do not change
    partial = tv.render(tv.load_scene(_scene(sky_blend=0.01)), dtype=F64)
    assert float((partial.radiance - near.radiance).abs().max()) > 1e-3


def test_ambient_alone_lies_between_its_colours_graded_by_altitude():
    """No light, no sky: each sample's source is σs · mix(bottom, top, h) with h the altitude in the
    shell (not y: over a small planet the two differ), so the pixel is albedo · ∫ T σt ambient dt,
    between albedo · alpha · bottom and albedo · alpha · top per channel, and nearer the bottom for a
    layer seen from below."""
    density = {"bottom": 1.0, "top": 3.0, "coverage": 0.7, "planet_radius": 20.0}
    scene = _scene(bounds={"shell": {"planet_radius": 20.0, "bottom": 1.0, "top": 3.0}}, density={"cloudscape": density},
                   ambient=SEEDS_AMBIENT)
    scene.update(lights=[])
    del scene["sky"]
    out = tv.render(tv.load_scene(scene), dtype=F64)
    alpha = out.alpha[0, 0]
    assert float(alpha.max()) > 0.5
    lo = torch.tensor(SEEDS_AMBIENT["radiance"], dtype=F64)[:, None, None] * 0.9 * alpha
    hi = torch.tensor(SEEDS_AMBIENT["top"], dtype=F64)[:, None, None] * 0.9 * alpha
    assert torch.all(out.radiance[0] >= lo - 1e-9) and torch.all(out.radiance[0] <= hi + 1e-9)
    assert float((out.radiance[0] - lo).max()) > 1e-3


def test_plan_turns_the_new_terms_on_only_when_asked():
    plain = make_plan(tv.load_scene(_scene())).volumes[0]
    assert not plain.ambient and not plain.sky_blend
    asked = make_plan(tv.load_scene(_scene(ambient=SEEDS_AMBIENT, sky_blend=0.01))).volumes[0]
    assert asked.ambient and asked.sky_blend
    # a blend makes the source vary along the ray: a homogeneous medium is marched, not closed
    box = {"bounds": {"box": {}}, "density": {"constant": 1.0}, "phase": "isotropic"}
    scene = {**_scene(**box), "lights": [{"kind": "sun", "direction": [0.0, 1.0, 0.0]}]}
    assert make_plan(tv.load_scene(scene)).volumes[0].strategy == "closed_form"
    assert make_plan(tv.load_scene({**scene, "volumes": [{**scene["volumes"][0], "sky_blend": 0.1}]})).volumes[0].strategy == "march"


@pytest.mark.parametrize("size", [(7, 5), (1, 1), (13, 3)])
def test_finite_renders_at_odd_sizes(size):
    scene = _scene(density={"cloudscape": {"bottom": 1.0, "top": 3.0, "coverage": 0.8, "planet_radius": 200.0,
                                           "wind": [0.5, 0.0, 0.2]}}, sky_blend=0.002, ambient=SEEDS_AMBIENT)
    scene["image"] = {"width": size[0], "height": size[1]}
    scene["time"] = 2.0
    out = tv.render(tv.load_scene(scene))
    assert out.image.shape == (1, 3, size[1], size[0])
    for t in (out.image, out.radiance, out.depth, out.alpha):
        assert torch.all(torch.isfinite(t))
    assert out.stats["passes"] == ["rays", "sky", "volume0.march", "volume0.shadow0", "composite"]


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True)
@given(k=st.sampled_from([1e-12, 1e-3, 1e6, 1e30]), sigma=st.sampled_from([0.0, 1e-12, 1e3, 1e7]),
       coverage=st.sampled_from([0.0, 0.5, 1.0]), erosion=st.sampled_from([0.0, 5.0]),
       cloud_type=st.sampled_from([0.0, 1.0]), curved=st.booleans())
def test_hard_cases_stay_finite(k, sigma, coverage, erosion, cloud_type, curved):
    density = {"bottom": 1.0, "top": 3.0, "coverage": coverage, "erosion": erosion, "type": cloud_type}
    bounds = {"slab": {"y_min": 1.0, "y_max": 3.0}}
    if curved:
        density["planet_radius"] = 50.0
        bounds = {"shell": {"planet_radius": 50.0, "bottom": 1.0, "top": 3.0}}
    scene = _scene(bounds=bounds, density={"cloudscape": density}, sigma_t=sigma, sky_blend=k, ambient=SEEDS_AMBIENT)
    scene["image"] = {"width": 7, "height": 5}
    out = tv.render(tv.load_scene(scene))
    for t in (out.image, out.radiance, out.depth, out.alpha):
        assert torch.all(torch.isfinite(t))
    assert float(out.alpha.min()) >= 0.0 and float(out.alpha.max()) <= 1.0


def test_refusals_name_the_key():
    with pytest.raises(ValueError, match=r"volumes\[0\].density.cloudscape"):
        tv.load_scene(_scene(density={"cloudscape": {"bottom": 3.0, "top": 1.0}}))
    with pytest.raises(ValueError, match=r"coverage"):
        tv.load_scene(_scene(density={"cloudscape": {"coverage": 1.5}}))
    with pytest.raises(ValueError, match=r"sky_blend"):
        tv.load_scene(_scene(sky_blend=-1.0))
    with pytest.raises(ValueError, match=r"volumes\[0\]\.sky_blend.*a term of the physical medium"):
        tv.load_scene(_scene(sky_blend=0.1, shading="shader"))
    with pytest.raises(ValueError, match=r"volumes\[0\]\.ambient.*a term of the physical medium"):
        tv.load_scene(_scene(ambient=SEEDS_AMBIENT, shading="shader"))


def test_preset_renders_a_sky_of_clouds():
    out = tv.render(tv.preset("cloudscape", width=24, height=24))
    assert out.stats["passes"] == ["rays", "sky", "volume0.march", "volume0.shadow0", "composite", "post.tonemap.aces"]
    assert torch.all(torch.isfinite(out.image))
    top = out.alpha[0, 0, :12]
    assert 0.1 < float(top.mean()) < 0.95  # scattered clouds: some sky shows through
    scene = tv.preset("cloudscape", width=8, height=8, coverage=0.9, cloud_type=0.1, sun_elevation=30.0, time=2.0)
    vol, sun = scene.volumes[0].density.cloudscape, scene.lights[0].direction
    assert (vol.coverage, vol.type, scene.time) == (0.9, 0.1, 2.0)
    assert math.isclose(math.degrees(math.asin(sun[1] / math.hypot(*sun))), 30.0, abs_tol=1e-9)
    with pytest.raises(ValueError, match="cloudscape.sun_elevation"):
        tv.preset("cloudscape", sun_elevation=95.0)


# ---------------------------------------------------------------------------------------------
# dual-lobe HG against the seeds' GLSL (Mesa llvmpipe)

_HG_GLSL = """
float HenyeyGreenstein(float cosTheta, float g) {
    float gg = g * g;
    return (1.0 - gg) / pow(1.0 + gg - 2.0 * g * cosTheta, 1.5);
}
uniform vec3 lobes;
void mainImage(out vec4 fragColor, in vec2 fragCoord) {
    float sundotrd = -1.0 + 2.0 * fragCoord.x / iResolution.x;
    float scattering = mix(HenyeyGreenstein(sundotrd, lobes.x), HenyeyGreenstein(sundotrd, lobes.y), lobes.z);
    fragColor = vec4(scattering, sundotrd, 0.0, 1.0);
}
"""


@pytest.mark.parametrize("lobes", [(0.8, -0.2, 0.5), (0.6, -0.3, 0.4), (0.95, 0.1, 0.8)])
def test_dual_hg_matches_the_seeds_glsl(lobes):
    glsl = pytest.importorskip("torchvol.measure.glsl")
    if glsl.gl_context() is None:
        pytest.skip("no OpenGL (moderngl/EGL) context")
    out = glsl.run_fragment(glsl.shadertoy_source(_HG_GLSL), 256, 1, uniforms={"lobes": lobes})
    seeds, cos = out[0, :, 0].astype(np.float64), torch.from_numpy(out[0, :, 1].astype(np.float64))
    # the seeds' HG omits 1/4π; it takes the same cosine once its sun direction points towards the sun
    ours = dual_henyey_greenstein(cos, *lobes).numpy() * 4.0 * math.pi
    # the seeds' float32 1 + g² − 2g·cos cancels near a lobe's peak: its rounding (a few ulp of the
    # terms) grows by the cancellation (terms / result) and the power 1.5
    c = cos.numpy()
    cancel = np.maximum(*[(1 + g * g + 2 * abs(g)) / (1 + g * g - 2 * g * c) for g in lobes[:2]])
    assert np.all(np.abs(ours - seeds) <= 4 * 2.0**-24 * 1.5 * cancel * np.abs(ours))


# ---------------------------------------------------------------------------------------------
# the planet's shell


def test_shell_bounds_first_stretch_and_the_ground():
    from torchvol.geometry.rays import intersect_shell

    R, lo, hi = 100.0, 2.0, 5.0
    c = torch.tensor([0.0, -R, 0.0], dtype=F64)
    o = torch.tensor([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 3.0, 0.0], [0.0, 3.0, 0.0], [0.0, 8.0, 0.0],
                      [0.0, 8.0, 0.0], [0.0, 1.0, 0.0]], dtype=F64)
    d = torch.tensor([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [0.0, -1.0, 0.0],
                      [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]], dtype=F64)
    t0, t1 = intersect_shell(o, d, c, R, R + lo, R + hi)
    # straight up from below: floor to ceiling; down from below: the ground hides the far side
    assert_close(torch.stack([t0[0], t1[0]]), torch.tensor([1.0, 4.0], dtype=F64), atol=1e-9, what="up from below")
    assert float(t0[1]) > float(t1[1])
    # inside the layer: up to the ceiling, or down to the floor
    assert_close(torch.stack([t0[2], t1[2], t0[3], t1[3]]), torch.tensor([0.0, 2.0, 0.0, 1.0], dtype=F64), atol=1e-9, what="inside")
    # from above: down from the ceiling to the floor; up: nothing
    assert_close(torch.stack([t0[4], t1[4]]), torch.tensor([3.0, 6.0], dtype=F64), atol=1e-9, what="down from above")
    assert float(t0[5]) > float(t1[5])
    # horizontal from below: the layer's floor curves down to meet the ray
    r1 = R + 1.0
    assert_close(torch.stack([t0[6], t1[6]]), torch.tensor([math.sqrt((R + lo) ** 2 - r1**2), math.sqrt((R + hi) ** 2 - r1**2)], dtype=F64),
                 atol=1e-9, what="horizontal")


@pytest.mark.skipif(not drjit_available(), reason="Dr.Jit's LLVM backend is not available")
def test_the_shell_interval_traced_by_drjit_is_intersect_shells():
    """`shell_interval` (the shell's ``lanes`` interval, what a kernel's rays and shadow rays take)
    traced by Dr.Jit against `intersect_shell` (the same function on torch columns): rays from
    below, inside and above the layer, grazing it and the ground; the same misses, the distances
    within float32's rounding (Dr.Jit's fast-math square root: an ulp)."""
    from torchvol.geometry.bounds import BOUNDS, Shell, bounds_lanes
    from torchvol.geometry.rays import intersect_shell

    g = torch.Generator().manual_seed(4)
    n, radius = 20000, 300.0
    o = (torch.rand(n, 3, generator=g) * 2 - 1) * torch.tensor([30.0, 5.0, 30.0]) + torch.tensor([0.0, 3.0, 0.0])
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g) * torch.tensor([1.0, 0.1, 1.0]), dim=1)  # mostly grazing
    bounds = stack([Shell(planet_radius=radius, bottom=1.0, top=3.0)])
    s = torch.zeros(n, dtype=torch.long)
    _, lane = _drjit_lanes(s)
    traced = BOUNDS["shell"].caps["lanes"][0](bounds_lanes(bounds, lambda v: lane(take(v, s))), lane(o), lane(d))
    t0, t1 = intersect_shell(o, d, torch.tensor([0.0, -radius, 0.0]), radius, radius + 1.0, radius + 3.0)
    for got, want in zip(traced, (t0, t1)):
        got = torch.from_numpy(np.array(got))
        assert torch.equal(torch.isinf(got), torch.isinf(want)) and float(torch.isinf(want).float().mean()) > 0.1
        hit = torch.isfinite(want)
        assert_close(got[hit] / want[hit].abs().clamp_min(1.0), want[hit] / want[hit].abs().clamp_min(1.0), atol=1e-6,
                     what="shell interval, relative")


def test_shell_layer_renders_over_the_curved_ground():
    scene = _scene(bounds={"shell": {"planet_radius": 200.0, "bottom": 1.0, "top": 3.0}},
                   density={"cloudscape": {"bottom": 1.0, "top": 3.0, "planet_radius": 200.0, "coverage": 0.8}})
    scene["camera"] = {"eye": [0.0, 0.5, 0.0], "target": [0.0, 0.0, 6.0], "fov_y": 80.0}  # half the view below the horizon
    out = tv.render(tv.load_scene(scene))
    assert torch.all(torch.isfinite(out.image))
    alpha = out.alpha[0, 0]
    assert float(alpha[:3].mean()) > 0.2 and torch.all(alpha[-3:] == 0)  # clouds above, none through the ground
