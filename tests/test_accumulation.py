"""Progressive accumulation (`image.passes`): one pass is the render without it, to the bit; the
running mean and the exponential blend are their formulas over single renders at the passes'
seeds; the mean converges towards a many-step reference; passes are deterministic per (seed, index)."""

import pytest
import torch

import torchvol as tv
from tests.conftest import assert_close
from torchvol.renderer.accumulate import pass_seeds


def puff(**keys):
    return tv.load_scene(tv.preset("cloud-puff", width=12, height=10), {"march.steps": 6, "lights[0].shadow.steps": 3, **keys})


def single_passes(scene, seed: int, n: int):
    """Pass k alone: the scene rendered with pass k's seed."""
    seeds = torch.tensor([seed])
    return [tv.render(scene, seed=int(pass_seeds(seeds, k)[0])) for k in range(n)]


def test_one_pass_is_the_render_without_accumulation(one_thread):
    a, b = tv.render(puff(), seed=5), tv.render(puff(**{"image.passes": 1, "image.blend": "exponential"}), seed=5)
    for key in ("image", "radiance", "depth", "alpha"):
        assert torch.equal(getattr(a, key), getattr(b, key)), key
    assert a.aovs.keys() == b.aovs.keys() and all(torch.equal(a.aovs[k], b.aovs[k]) for k in a.aovs)
    assert b.stats["plan"]["passes"] == a.stats["plan"]["passes"] and "accumulate" not in b.stats["passes"] and "accumulation" not in b.stats


def test_pass_zero_keeps_the_scene_seed_and_later_seeds_differ():
    seeds = torch.tensor([0, 7, 2**32 - 1])
    assert torch.equal(pass_seeds(seeds, 0), seeds)
    later = torch.stack([pass_seeds(seeds, k) for k in range(1, 6)])
    assert len(set(later.flatten().tolist()) | set(seeds.tolist())) == 18
    assert ((later >= 0) & (later < 2**32)).all()
    assert torch.equal(pass_seeds(seeds, 3), pass_seeds(seeds.clone(), 3))


def test_running_mean_is_the_mean_of_the_single_passes(one_thread):
    out = tv.render(puff(**{"image.passes": 3}), seed=4)
    singles = single_passes(puff(), 4, 3)
    expected = (singles[0].radiance + singles[1].radiance) + singles[2].radiance
    assert torch.equal(out.radiance, expected / 3)
    assert_close(out.alpha, sum(s.alpha for s in singles) / 3, atol=1e-6, what="alpha")
    hits = sum((s.depth > 0).float() for s in singles)  # depth: the mean over the passes that hit
    assert_close(out.depth, sum(s.depth for s in singles) / hits.clamp_min(1), atol=1e-5, what="depth")
    assert out.stats["passes"][-2:] == ["accumulate", "post.tonemap.aces"] and out.stats["plan"]["passes"] == out.stats["passes"]
    changes = out.stats["accumulation"]
    assert len(changes) == 2 and all(c > 0 for c in changes)
    assert changes[0] == pytest.approx(float((singles[1].radiance - singles[0].radiance).abs().mean()) / 2, rel=1e-5)


def test_exponential_blend_is_the_seeds_mix(one_thread):
    w = 0.3
    out = tv.render(puff(**{"image.passes": 3, "image.blend": "exponential", "image.blend_weight": w}), seed=1)
    r = [s.radiance for s in single_passes(puff(), 1, 3)]
    expected = torch.lerp(torch.lerp(r[0], r[1], torch.tensor(w)), r[2], torch.tensor(w))
    assert_close(out.radiance, expected, atol=1e-6, what="mix(mix(p0, p1, w), p2, w)")
    assert_close(out.radiance, 0.49 * r[0] + 0.21 * r[1] + 0.3 * r[2], atol=1e-5, what="weights")


def test_mean_converges_towards_a_many_step_reference(one_thread):
    reference = tv.render(puff(**{"march.steps": 256, "march.dither": "none"})).radiance
    errors = [float((tv.render(puff(**{"image.passes": n}), seed=2).radiance - reference).abs().mean()) for n in (1, 4, 16)]
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 0.7 * errors[0]


def test_deterministic_per_seed_and_batched_like_alone(one_thread):
    scene = puff(**{"image.passes": 3})
    a, b, c = tv.render(scene, seed=9), tv.render(scene, seed=9), tv.render(scene, seed=10)
    assert torch.equal(a.image, b.image) and not torch.equal(a.image, c.image)
    other = puff(**{"image.passes": 3, "image.blend_weight": 0.5, "volumes[0].sigma_t": 3.0})
    both = tv.render([scene, other], seed=[9, 3])
    assert torch.equal(both.radiance[:1], a.radiance)
    assert torch.equal(both.radiance[1:], tv.render(other, seed=3).radiance)
    assert torch.equal(tv.render(scene, seed=9, chunk_rays=17).radiance, a.radiance)


@pytest.mark.parametrize("size", [(1, 1), (5, 3), (9, 7)])
@pytest.mark.parametrize("blend", ["mean", "exponential"])
def test_odd_sizes_are_finite(size, blend, one_thread):
    scene = tv.load_scene(puff(), {"image.width": size[0], "image.height": size[1], "image.passes": 3, "image.blend": blend,
                                   "image.spp": 2})
    out = tv.render(scene)
    assert out.image.shape == (1, 3, size[1], size[0])
    assert all(t.isfinite().all() for t in (out.image, out.radiance, out.depth, out.alpha))


def test_passes_that_could_not_differ_are_refused():
    with pytest.raises(ValueError, match=r"image\.passes: got 4.*march\.dither = 'hash'"):
        tv.render(puff(**{"image.passes": 4, "march.dither": "none"}))
    tv.render(puff(**{"image.passes": 2, "march.dither": "none", "image.spp": 2}))  # the jitter differs
    for key, value in (("image.passes", 0), ("image.blend", "median"), ("image.blend_weight", 0.0)):
        with pytest.raises(ValueError, match=key.replace(".", r"\.")):
            puff(**{key: value})
