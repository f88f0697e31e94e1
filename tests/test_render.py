"""Render-level invariants: chunking, batching, seeds, spp, presets, validation at the boundary."""

import numpy as np
import pytest
import torch

import torchvol as tv

PUFF = dict(width=20, height=14)


def small(name, **params):
    scene = tv.preset(name, **{**PUFF, **params})
    if name == "cloud-puff":  # cheap but still shadowed and marched
        scene = tv.load_scene(scene, {"march.steps": 16, "lights[0].shadow.steps": 3})
    return scene


@pytest.mark.parametrize("name", ["cloud-puff", "template-clouds", "homogeneous-box"])
def test_chunk_size_does_not_change_the_image(name):
    scene = tv.load_scene(small(name), {"image.spp": 2} if name != "template-clouds" else None)
    whole = tv.render(scene, seed=3)
    pieces = tv.render(scene, seed=3, chunk_rays=37)
    for key in ("image", "radiance", "alpha", "depth"):
        diff = (getattr(whole, key) - getattr(pieces, key)).abs().max().item()
        assert diff <= 1e-6, f"{key}: chunked render differs by {diff}"


def test_batch_equals_single_renders():
    a = tv.load_scene(small("cloud-puff"), {"volumes[0].sigma_t": 4.0, "camera.eye": [0.3, 0.5, -3.0]})
    b = tv.load_scene(small("cloud-puff"), {"volumes[0].sigma_t": 20.0, "lights[0].direction": [-1, 0.5, 0]})
    both = tv.render([a, b])
    for i, scene in enumerate((a, b)):
        single = tv.render(scene)
        diff = (both.image[i] - single.image[0]).abs().max().item()
        assert diff <= 1e-5, f"scene {i} rendered in a batch differs from alone by {diff}"
        assert torch.equal(both.camera.K[i], single.camera.K[0])


def test_same_seed_same_image_other_seed_other_dither():
    scene = small("cloud-puff")
    first, again, other = tv.render(scene, seed=1), tv.render(scene, seed=1), tv.render(scene, seed=2)
    assert torch.equal(first.image, again.image)
    assert not torch.equal(first.radiance, other.radiance)


def test_spp_averages_stratified_samples():
    scene = tv.load_scene(small("homogeneous-box"), {"image.spp": 4})
    out = tv.render(scene)
    assert out.image.shape == (1, 3, 14, 20) and out.stats["rays"] == 20 * 14 * 4
    assert "resolve" in out.stats["passes"]
    one = tv.render(small("homogeneous-box"))
    # sub-pixel samples blur the silhouette a little, nothing more
    assert (out.alpha - one.alpha).abs().mean() < 0.05


def test_outputs_follow_design_shapes_and_dtypes():
    out = tv.render(small("cloud-puff"))
    assert out.image.shape == out.radiance.shape == (1, 3, 14, 20)
    assert out.depth.shape == out.alpha.shape == (1, 1, 14, 20)
    assert all(v.dtype == torch.float32 for v in (out.image, out.radiance, out.depth, out.alpha))
    assert set(out.aovs) == {"depth_median", "distance"}
    assert out.camera.K.shape == (1, 3, 3) and out.camera.world_to_camera.shape == (1, 4, 4)
    assert list(out.stats["time_s"]) == out.stats["passes"]
    assert out.image.min() >= 0 and out.image.max() <= 1


def test_reference_quality_renders_in_float64():
    out = tv.render(tv.load_scene(small("homogeneous-box"), {"march.quality": "reference", "march.closed_form": False}))
    assert out.stats["dtype"] == "float64" and out.image.dtype == torch.float32


def test_load_scene_sources_agree(tmp_path):
    import tomllib

    from torchvol.scene.model import PRESET_DIR

    path = PRESET_DIR / "cloud-puff.toml"
    with open(path, "rb") as f:
        data = tomllib.load(f)
    assert tv.load_scene(path) == tv.load_scene(data) == tv.load_scene("cloud-puff") == tv.preset("cloud-puff")
    s = tv.load_scene("cloud-puff", {"camera.fov_y": 30, "volumes.0.sigma_t": 2.5})
    assert s.camera.fov_y == 30 and s.volumes[0].sigma_t == 2.5


@pytest.mark.parametrize(
    "overrides,path",
    [({"volumes[3].sigma_t": 1}, "volumes[3]"), ({"image.width": 0}, "image.width"), ({"post.tonemap": "agx"}, "post.tonemap")],
)
def test_bad_overrides_name_the_key(overrides, path):
    with pytest.raises(ValueError) as err:
        tv.load_scene("cloud-puff", overrides)
    assert str(err.value).startswith(path), str(err.value)


def test_unknown_preset_and_parameter_are_refused():
    with pytest.raises(ValueError, match="template-clouds"):
        tv.preset("template-cloud")
    with pytest.raises(ValueError, match="did you mean 'mouse'"):
        tv.preset("template-clouds", mose=(1, 2))


def test_template_preset_parameters_move_the_camera():
    a = tv.preset("template-clouds", mouse=(100.0, 50.0), width=200, height=100, time=4.0)
    m = np.array([100 / 200, 50 / 100])
    ro = 4 * np.array([np.sin(3 * m[0]), 0.8 * m[1], np.cos(3 * m[0])]) / np.linalg.norm([np.sin(3 * m[0]), 0.8 * m[1], np.cos(3 * m[0])])
    ro[1] += 0.5
    assert np.allclose(a.camera.eye, ro) and a.time == 4.0
    cr = 0.07 * np.cos(0.25 * 4.0)
    assert np.allclose(a.camera.up, [np.sin(cr), np.cos(cr), 0.0])


def test_height_ambient_gradient_darkens_the_cloud_base():
    """Seed Step 6 Method C: ambient = mix(bottom, top, normalised height) in the shader look."""
    base = tv.preset("template-clouds", width=32, height=18)
    flat = tv.load_scene(base, {"volumes[0].shader.ambient": [0.2, 0.2, 0.2]})
    graded = tv.load_scene(flat, {"volumes[0].shader.ambient_top": [1.0, 1.0, 1.0]})
    a, b = tv.render(flat), tv.render(graded)
    cloudy = a.alpha > 0.3
    assert cloudy.any() and (b.radiance - a.radiance)[cloudy.expand_as(a.radiance)].min() >= 0
    assert (b.radiance - a.radiance).max() > 0.05


@pytest.mark.parametrize("kwargs,key", [
    ({"device": "nope"}, "device"), ({"dtype": torch.int32}, "dtype"), ({"chunk_rays": 0}, "chunk_rays"),
    ({"seed": "a"}, "seed"), ({"seed": [1, 2]}, "seed"),
])
def test_bad_render_arguments_name_the_argument(kwargs, key):
    with pytest.raises(ValueError) as err:
        tv.render(small("homogeneous-box"), **kwargs)
    assert str(err.value).startswith(key), str(err.value)


@pytest.mark.parametrize("spp", [1, 2, 4])
@pytest.mark.parametrize("key", ["radiance", "material", "ao", "depth"])
def test_resolve_into_is_the_resolve_of_each_mode(key, spp):
    """`resolve_into` writes, bitwise (signed zeros included), what each output's resolve rule
    gives: the mean over the sub-samples (of one: x + 0, −0 becoming +0 as the mean makes it), the
    first sub-sample (ids), or the mean over the sub-samples that hit."""
    from torchvol.renderer.aovs import RESOLVE
    from torchvol.renderer.executor import resolve_into

    g = torch.Generator().manual_seed(spp)
    values = torch.randn(37, spp, 3, generator=g).clamp_min(0.0)
    values[::5] = -0.0
    mode = RESOLVE[key]
    want = {"first": values[:, 0], "mean": values.mean(dim=1)}.get(
        mode, values.sum(dim=1) / (values > 0).sum(dim=1).clamp_min(1))
    out = torch.full((3, 50), torch.nan)
    resolve_into(out[:, 5:42], values, key, spp)
    assert torch.equal(out[:, 5:42].T.contiguous().view(torch.int32), want.contiguous().view(torch.int32))
    assert out[:, :5].isnan().all() and out[:, 42:].isnan().all()
