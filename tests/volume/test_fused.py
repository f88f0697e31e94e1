"""The fused march step (`torchvol.volume.fused`): its eager twin against the generic march
(bitwise: same ops per ray), its wavefronts against one batch, the integer texture noise against
the float64 one (bitwise), and the compiled kernels against the eager twin (a stated tolerance)."""

import pytest
import torch
from conftest import assert_close
from hypothesis import given, settings
from hypothesis import strategies as st

import torchvol as tv
from torchvol.noise import lattice as noise
from torchvol.renderer.plan import fused_march, make_plan
from torchvol.scene.model import load_scene
from torchvol.schema.batch import stack
from torchvol.volume import fused, strategy


def _template(width=24, height=14, **changes):
    scene = tv.preset("template-clouds", width=width, height=height).model_dump()
    for path, value in changes.items():  # "volumes.0.shader.fog": a key path, list indices as numbers
        *parents, last = path.split(".")
        target = scene
        for key in parents:
            target = target[int(key)] if key.isdigit() else target[key]
        target[last] = value
    return load_scene(scene)


@pytest.fixture
def eager_twin(monkeypatch):
    """`render(..., compile=True)` runs the fused path's eager twin (nothing compiles); the list
    it yields counts the fused marches that ran."""
    calls = []

    def twin(*args, **kwargs):
        calls.append(1)
        return fused.march_fused(*args, compiled=False, **kwargs)

    monkeypatch.setattr(strategy, "march_fused", twin)
    return calls


def _assert_same(fast, slow, what):
    for name in ("image", "radiance", "alpha", "depth"):
        a, b = getattr(fast, name), getattr(slow, name)
        assert torch.equal(a, b), f"{what}: {name} differs by {float((a - b).abs().max()):.3e}"
    assert fast.stats["march_steps"] == slow.stats["march_steps"]
    assert fast.stats["density_evals"] == slow.stats["density_evals"]


VARIANTS = {
    "template": {},
    "camera inside the layer": {"camera.eye": [0.3, 0.5, 0.2], "camera.target": [1.0, 0.7, -3.0]},
    "camera level with the layer top": {"camera.eye": [0.0, 2.0, 4.0], "camera.target": [0.0, 2.0, 0.0]},
    "height-graded ambient, no fog": {"volumes.0.shader.ambient_top": [0.9, 0.95, 1.1], "volumes.0.shader.fog": 0.0},
    "no derivative light": {"volumes.0.shader.light": "none"},
    "hash dither, count placement, no LOD": {"march.dither": "hash", "march.placement": "count", "march.steps": 24,
                                             "march.lod": None},
    "no density": {"volumes.0.density.clouds.bias": -9.0},
    "opaque: every sample at density 1": {"volumes.0.density.clouds.bias": 9.0, "march.min_transmittance": 0.0},
    "step limit truncates": {"march.steps": 6},
}


@pytest.mark.parametrize("name", list(VARIANTS))
def test_eager_twin_is_the_generic_march_bitwise(name, eager_twin, one_thread):
    scene = _template(**VARIANTS[name])
    _assert_same(tv.render(scene, compile=True), tv.render(scene), name)
    assert eager_twin, "the fused path did not run"


def test_eager_twin_on_a_batch_of_scenes_bitwise(eager_twin, one_thread):
    """Two scenes of another texture seed, time, wind, light and look in one batch: each texture
    is its own rows of the stacked table."""
    scenes = [_template(), _template(time=3.5, **{"volumes.0.density.clouds.texture_seed": 7,
                                                   "volumes.0.density.clouds.wind": [0.2, 0.0, 0.5],
                                                   "lights.0.direction": [0.3, 0.4, -0.8],
                                                   "volumes.0.shader.alpha_scale": 0.6})]
    fast, slow = tv.render(scenes, compile=True), tv.render(scenes)
    _assert_same(fast, slow, "batch")
    assert eager_twin and not torch.equal(fast.image[0], fast.image[1])


@pytest.mark.parametrize(("wavefront", "refill_every", "compact_below"),
                         [(7, 3, 0.875), (64, 1, 1.0), (10_000, 50, 0.875), (10_000, 4, 0.0), (10_000, 2, 1.0)])
def test_wavefront_size_refills_and_compaction_do_not_change_the_result(wavefront, refill_every, compact_below, monkeypatch,
                                                                        eager_twin, one_thread):
    """Finished slots ride along until live ones fall below `compact_below` of the wavefront (0:
    until none is live; 1: dropped at once)."""
    scene = _template(16, 10)
    expected = tv.render(scene)
    monkeypatch.setattr(fused, "WAVEFRONT", wavefront)
    monkeypatch.setattr(fused, "REFILL_EVERY", refill_every)
    monkeypatch.setattr(fused, "COMPACT_BELOW", compact_below)
    _assert_same(tv.render(scene, compile=True), expected,
                 f"wavefront {wavefront}, refill every {refill_every}, compact below {compact_below}")


def test_fused_path_runs_only_where_the_scene_is_the_template_technique():
    """`plan.fused_march`: the shader look over the cloud layer, lit by suns; not the physical
    clouds, not a cloud layer with an edge falloff or lit by a point light."""
    def volume_fusable(scene) -> bool:
        batch = stack([scene])
        plan = make_plan(batch, compile="all")
        return fused_march(batch, batch.volumes[0], plan.volumes[0].lights)

    assert volume_fusable(_template())
    assert not volume_fusable(tv.preset("cloud-puff", width=8, height=8))
    point = _template().model_dump()
    point["lights"] = [{"kind": "point", "position": [0.0, 3.0, 0.0], "intensity": 2.0}]
    point["sky"].update(halo=None, flare=None)  # (they need a sun)
    assert not volume_fusable(load_scene(point))


def _stacked_tables(seeds):
    tables = [noise.texture_table(noise.default_noise_texture(s)) for s in seeds]
    return tables, noise.packed_table(torch.cat(tables))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_integer_texture_noise_is_the_float64_one_bitwise(dtype):
    """`noise.texture_noise_coords` (int32/int64 steps, stacked tables) against
    `noise.texture_noise_table` (float64 steps): every value equal, also past the float->int32
    overflow and at NaN."""
    tables, packed = _stacked_tables([0, 5])
    p = hard_points(dtype)
    s = torch.arange(p.shape[0]) % 2
    expected = torch.where(s == 0, noise.texture_noise_table(p, tables[0]), noise.texture_noise_table(p, tables[1]))
    assert_same_values(noise.texture_noise_coords(*p.unbind(1), packed, s * 65536), expected, p)


def hard_points(dtype=torch.float32):
    """[80,004, 3] points from |p| ≤ 2 to 5·10⁷, past the float->int32 overflow, and NaN."""
    g = torch.Generator().manual_seed(1)
    return torch.cat([(torch.rand(20000, 3, generator=g, dtype=dtype) - 0.5) * scale for scale in (4.0, 400.0, 1e5, 1e8)]
                     + [torch.tensor([[float("nan"), 0, 0], [1e30, 1, 2], [-1e30, 1, 2], [0.5, 0.5, 1e7]], dtype=dtype)])


def assert_same_values(got, expected, p):
    """Every value equal (NaN where NaN), else how many differ and the first point."""
    same = (got == expected) | (got.isnan() & expected.isnan())
    assert same.all(), f"{int((~same).sum())} of {len(p)} differ, first at {p[~same][0].tolist()}"


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-3e9, 3e9, allow_nan=False, width=32), min_size=3, max_size=3))
def test_integer_texture_noise_is_bitwise_at_any_float32_point(xyz):
    tables, packed = _stacked_tables([3])
    p = torch.tensor([xyz], dtype=torch.float32)
    assert torch.equal(noise.texture_noise_coords(*p.unbind(1), packed), noise.texture_noise_table(p, tables[0]))


@pytest.mark.slow  # compiles the step's three kernels (inductor's on-disk cache serves later runs)
def test_compiled_step_matches_the_eager_twin(inductor_march):
    """Inductor contracts multiply-adds and vectorises exp/log: an ulp of a texture coordinate
    moves the 8-bit filter by 1/255 at a few points. Measured: image within 7e-7, depth 3e-6."""
    scenes = [_template(40, 24), _template(40, 24, time=2.0, **{"volumes.0.density.clouds.texture_seed": 4})]
    fast, slow = tv.render(scenes, compile=True), tv.render(scenes)
    assert_close(fast.image, slow.image, atol=1e-5, what="image")
    assert_close(fast.alpha, slow.alpha, atol=1e-5, what="alpha")
    assert_close(fast.depth, slow.depth, atol=1e-4, what="depth")
    assert fast.stats["density_evals"] == slow.stats["density_evals"]


def test_compiled_datasets_take_the_fused_path(eager_twin, one_thread):
    """`SceneDataset(compile=True)` and `render_samples(compile=True)` (what `generate --compile`
    runs) reach the fused step for the template recipe (here its eager twin: same bytes as eager)."""
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "datasets" / "template-clouds.toml"
    tiny = {"image.width": 12, "image.height": 8}
    fast, slow = tv.SceneDataset(path, 2, overrides=tiny, compile=True), tv.SceneDataset(path, 2, overrides=tiny, compile="off")
    for i in range(2):
        assert torch.equal(fast[i]["image"], slow[i]["image"])
    assert len(eager_twin) == 2
