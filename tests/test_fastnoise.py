"""The arithmetic-hash value-noise fBm (`torchvol.noise.fast`): its hash against a uint32 reference,
its statistics against the table hash's, the compiled kernel against its eager twin."""

import pytest
import torch
from conftest import assert_close

import torchvol as tv
from torchvol.noise import fast as fastnoise
from torchvol.noise import lattice as noise
from torchvol.renderer.plan import compile_pays


def _points(n: int, seed: int = 0, dtype=torch.float32) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=g, dtype=torch.float64) * 40.0 - 20.0).to(dtype)


def _reference_hash(x: int, y: int, z: int, seed: int) -> int:
    """`fastnoise.hash_cells` in Python uint32 arithmetic (what the int32 wrap must equal)."""
    m = 0xFFFFFFFF

    def mix(h: int) -> int:
        h ^= h >> 16
        h = (h * 0x7FEB352D) & m
        h ^= h >> 15
        h = (h * 0x1B873593) & m
        return h ^ (h >> 16)

    s = mix((seed * 0x9E3779B9 + 0x632BE5AB) & m)
    h = mix(((x * 0x1B873593) ^ (y * 0x27D4EB2F) ^ (z * 0x165667B1) ^ s) & m)
    return h >> 8


def test_hash_equals_uint32_reference():
    cells = [(0, 0, 0), (1, -1, 7), (-40000, 123456, -9), (2**31 - 1, -(2**31), 5), (17, 17, 17)]
    x, y, z = (torch.tensor(c, dtype=torch.int32) for c in zip(*cells))
    for seed in (0, 1, 123456789, 2**40 + 3):
        got = fastnoise.hash_cells(x, y, z, fastnoise._seed32(seed)).tolist()
        assert got == [_reference_hash(*c, seed) for c in cells]


def test_value_noise_at_lattice_points_is_the_hash():
    g = torch.Generator().manual_seed(1)
    cells = torch.randint(-300, 300, (500, 3), generator=g, dtype=torch.int32)
    got = fastnoise.value_noise_hashed(cells.to(torch.float32), seed=5)
    want = fastnoise.hash_cells(*cells.unbind(-1), fastnoise._seed32(5)).to(torch.float32) * 2.0**-24
    assert torch.equal(got, want)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_value_noise_range_and_statistics_match_the_table_hash(dtype):
    p = _points(200_000, dtype=dtype)
    new = fastnoise.value_noise_hashed(p, seed=3)
    old = noise.value_noise(p, seed=3)
    assert new.dtype == dtype and bool(torch.isfinite(new).all())
    assert 0.0 <= new.min() and new.max() < 1.0
    assert abs(new.mean() - old.mean()) < 0.01  # both 0.5 in expectation
    assert abs(new.std() - old.std()) < 0.01
    assert abs(fastnoise.value_noise_hashed(p, seed=4).sub(0.5).mul(new - 0.5).mean()) < 2e-3  # seeds decorrelate


def test_fbm_spectrum_matches_the_table_hash():
    """Power spectra of a 2D slice of each 4-octave fBm, in octave bands, agree within 25%."""
    n = 256
    axis = torch.arange(n, dtype=torch.float64) * (8.0 / n)
    yy, xx = torch.meshgrid(axis, axis, indexing="ij")
    p = torch.stack([xx, yy, torch.full_like(xx, 0.37)], -1).reshape(-1, 3)

    def bands(values: torch.Tensor) -> torch.Tensor:
        power = torch.fft.rfft2((values - values.mean()).reshape(n, n)).abs().square()
        ky = torch.fft.fftfreq(n).abs()[:, None] * n
        kx = torch.fft.rfftfreq(n)[None, :] * n
        k = torch.sqrt(kx**2 + ky**2)
        edges = [2, 4, 8, 16, 32, 64]  # below 2 cycles per slice: too few modes to compare
        return torch.stack([power[(k >= a) & (k < b)].mean() for a, b in zip(edges, edges[1:])])

    old, new = torch.zeros(5, dtype=torch.float64), torch.zeros(5, dtype=torch.float64)
    for seed in range(4):  # average over seeds: one field's band powers scatter by ~10-20%
        old += bands(noise.fbm(p, lambda q: noise.value_noise(q, seed=seed), octaves=4))
        new += bands(fastnoise.fbm_value_hashed(p, seed=seed, octaves=4))
    ratio = new / old
    assert bool(((ratio > 0.75) & (ratio < 1.33)).all()), ratio


def test_eager_fbm_is_noise_fbm_of_the_hashed_basis():
    p = _points(1000)
    lod = torch.arange(1000) % 6
    got = fastnoise.fbm_value_hashed(p, seed=2, octaves=5, lod=lod)
    want = noise.fbm(p, lambda q: fastnoise.value_noise_hashed(q, seed=2), octaves=5, lod=lod)
    assert torch.equal(got, want)


def test_arithmetic_hash_refused_for_gradient_noise():
    scene = tv.preset("cloud-puff", width=8, height=8).model_dump()
    scene["volumes"][0]["density"]["fbm"].update(noise="perlin", hash="arithmetic")
    with pytest.raises(ValueError, match="hash"):
        tv.render(scene)


def test_scene_with_arithmetic_hash_renders_and_differs_from_table():
    scene = tv.preset("cloud-puff", width=12, height=12).model_dump()
    table = tv.render(scene)
    scene["volumes"][0]["density"]["fbm"]["hash"] = "arithmetic"
    arith = tv.render(scene)
    assert bool(torch.isfinite(arith.radiance).all())
    assert not torch.equal(arith.radiance, table.radiance)
    assert abs(arith.alpha.mean() - table.alpha.mean()) < 0.1  # the same cloud, another draw of its noise


@pytest.mark.slow  # torch.compile: ~20-100 s the first time on 2 cores (cached on disk after)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_fbm_matches_eager_twin(dtype):
    """Not bitwise: inductor's lerp and contraction differ from eager's by an ulp; stated tolerance
    4 ulp of 1 (the values lie in [0, 1))."""
    atol = 4 * torch.finfo(dtype).eps
    p = _points(5000, seed=3, dtype=dtype)
    lod = torch.arange(5000) % 6
    for kwargs in ({}, {"lod": lod}):
        eager = fastnoise.fbm_value_hashed(p, seed=11, octaves=4, **kwargs)
        fast = fastnoise.fbm_value_hashed(p, seed=11, octaves=4, compiled=True, **kwargs)
        assert_close(fast, eager, atol=atol, what=f"compiled fbm {kwargs.keys()}")
    # another size and seed: no recompile needed, same agreement
    q = p[:777]
    assert_close(fastnoise.fbm_value_hashed(q, seed=-4, octaves=4, compiled=True),
                 fastnoise.fbm_value_hashed(q, seed=-4, octaves=4), atol=atol)


@pytest.mark.slow
def test_compiled_render_matches_eager_render():
    scene = tv.preset("cloud-puff", width=16, height=16).model_dump()
    scene["volumes"][0]["density"]["fbm"]["hash"] = "arithmetic"
    eager, fast = tv.render(scene), tv.render(scene, compile=True)
    assert_close(fast.radiance, eager.radiance, atol=1e-5, what="radiance")
    assert_close(fast.alpha, eager.alpha, atol=1e-5, what="alpha")


@pytest.mark.slow
def test_compiled_fbm_field_matches_eager_field():
    """`fastnoise.fbm_field_hashed` (the whole signed fbm field as one kernel, what FbmField runs
    under compile) against FbmField's eager code, two scenes of another seed, frequency, offset and
    falloff in one batch, with and without LOD: within 1e-5 (density values up to ~10); bitwise the
    values of a scene alone."""
    from torchvol.fields.fbm import FbmField
    from torchvol.scene.model import load_scene
    from torchvol.schema.batch import stack

    scenes = []
    for seed, freq, radial in ((3, 2.2, 2.4), (77, 1.7, 0.0)):
        scene = tv.preset("cloud-puff", width=8, height=8).model_dump()
        scene["volumes"][0]["density"]["fbm"].update(hash="arithmetic", seed=seed, frequency=freq, radial=radial,
                                                     offset=[seed * 0.1, -1.0, 2.0], wind=[0.3, 0.0, 0.1])
        scenes.append(load_scene(scene))
    params = stack(scenes).volumes[0].density.value
    times = torch.tensor([0.0, 1.5])
    eager, fast = FbmField(params, times), FbmField(params, times, compiled=True)
    assert fast.fused_field and not eager.fused_field
    p = _points(3000, seed=5) * 0.06
    s = torch.arange(3000) % 2
    lod = torch.arange(3000) % 3
    for kwargs in ({}, {"lod": lod}):
        assert_close(fast.signed(p, s, **kwargs), eager.signed(p, s, **kwargs), atol=1e-5, what=f"field {kwargs.keys()}")
    assert_close(fast(p, s), eager(p, s), atol=1e-5, what="clamped field")
    # one kernel call for the batch: a scene's values are those it has rendered alone
    alone = FbmField(stack(scenes[1:]).volumes[0].density.value, times[1:], compiled=True)
    mine = s == 1
    assert torch.equal(alone.signed(p[mine], torch.zeros_like(s[mine])), fast.signed(p, s)[mine])


def test_compile_pays_only_for_scenes_of_fused_volumes():
    scene = tv.preset("cloud-puff", width=8, height=8).model_dump()
    assert not compile_pays(tv.preset("cloud-puff", width=8, height=8))  # the table hash
    scene["volumes"][0]["density"]["fbm"]["hash"] = "arithmetic"
    from torchvol.scene.model import load_scene
    assert compile_pays(load_scene(scene))
    assert compile_pays(tv.preset("template-clouds", width=8, height=8))  # the fused march step
    assert compile_pays(tv.preset("fur-ball", width=8, height=8))  # one Worley kernel
    assert not compile_pays(tv.preset("voxel-terrain", width=8, height=8))


@pytest.mark.slow  # compiles the fused field (cached on disk after the first run)
@pytest.mark.parametrize("name", ["clouds", "fur-ball"])
def test_generated_samples_compiled_match_eager(tmp_path, name):
    """`render_samples(..., compile=True)` (what `generate(..., compile=True)` runs)
    against eager: within 1e-5; `generate(compile=True)` writes a finished dataset."""
    from pathlib import Path

    from torchvol.dataset.datasets import render_samples
    from torchvol.dataset.generate import generate
    from torchvol.dataset.recipe import Recipe

    path = Path(__file__).resolve().parents[1] / "datasets" / f"{name}.toml"
    recipe = Recipe.load(path, {"image.width": 12, "image.height": 12})
    eager, fast = render_samples(recipe, [0, 1]), render_samples(recipe, [0, 1], compile=True)
    for a, b in zip(eager, fast):
        assert_close(b["image"], a["image"], atol=1e-5, what="image")
        assert_close(b["alpha"], a["alpha"], atol=1e-5, what="alpha")
        for depth in {"depth", "depth_median"} & a.keys():  # world units: a looser bound
            assert_close(b[depth], a[depth], atol=1e-4, what=depth)
    report = generate(path, count=1, out=tmp_path / "ds", overrides={"image.width": 8, "image.height": 8}, compile=True)
    assert report["finished"] and report["written"] == 1
