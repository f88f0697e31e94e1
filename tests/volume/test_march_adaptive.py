"""Error-controlled marching (step doubling) against a converged float64 reference."""

import functools

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import torchvol as tv
from torchvol.volume.march import StepRule, march, march_adaptive


def medium(ids, t, dt):
    """A varying medium along the ray: decaying exponential plus a ripple; source = σ·colour."""
    sigma = 3.0 * torch.exp(-2.0 * t) + 0.5 * torch.sin(7 * t) ** 2
    return sigma, sigma[:, None] * torch.tensor([1.0, 0.5, 0.25], dtype=t.dtype)


def shaded(ids, t, dt):
    """The same σ_t lit by a light that varies along the ray (as a shadow's transmittance does):
    the whole step's source, taken from the halves' per unit σ_t, is then not exact."""
    sigma, source = medium(ids, t, dt)
    return sigma, source * (1.0 + 0.8 * torch.sin(3.0 * t))[:, None]


def rays(n=48):
    t0 = torch.zeros(n, dtype=torch.float64)
    t1 = torch.linspace(0.2, 4.0, n, dtype=torch.float64)
    return t0, t1, torch.ones(n, dtype=torch.bool)


@pytest.mark.parametrize("lit", [medium, shaded], ids=["constant light", "varying light"])
@pytest.mark.parametrize("tolerance", [1e-2, 1e-3, 1e-4])
def test_error_stays_under_tolerance_and_the_estimate_bounds_it(tolerance, lit):
    t0, t1, hit = rays()
    ref = march(t0, t1, hit, lit, rule=StepRule("count", 20000), integrator="frostbite")
    out = march_adaptive(t0, t1, hit, lit, tolerance=tolerance)
    err = torch.maximum((out.transmittance - ref.transmittance).abs(), (out.radiance - ref.radiance).abs().amax(1))
    worst = int(err.argmax())
    assert err.max() <= tolerance, f"error {err.max():.2e} > {tolerance:.0e} on ray {worst}"
    assert (out.error >= err).all(), f"estimate {out.error[worst]:.2e} below the true error {err[worst]:.2e}"
    assert not out.truncated.any()


def test_tighter_tolerance_takes_more_samples():
    t0, t1, hit = rays()
    loose = march_adaptive(t0, t1, hit, medium, tolerance=1e-2).evaluations.sum()
    tight = march_adaptive(t0, t1, hit, medium, tolerance=1e-4).evaluations.sum()
    assert tight > 2 * loose


def test_empty_space_costs_few_samples():
    """A medium empty for 80% of the ray, then rising (continuously, as trilinear grids and noise
    do: no sampling estimate sees a jump between its samples). The adaptive march takes big steps
    through the empty part and beats a fixed march given the same number of samples."""
    def sparse(ids, t, dt):
        x = ((t - 8.0) / 2.0).clamp(0, 1)
        sigma = 6.0 * x**3
        return sigma, sigma[:, None].expand(-1, 3)

    t0 = torch.zeros(4, dtype=torch.float64)
    t1 = torch.full((4,), 10.0, dtype=torch.float64)
    hit = torch.ones(4, dtype=torch.bool)
    ref = march(t0, t1, hit, sparse, rule=StepRule("count", 20000), integrator="frostbite")
    out = march_adaptive(t0, t1, hit, sparse, tolerance=1e-2)
    adaptive_err = (out.transmittance - ref.transmittance).abs().max()
    fixed = march(t0, t1, hit, sparse, rule=StepRule("count", int(out.evaluations.max())), integrator="frostbite")
    fixed_err = (fixed.transmittance - ref.transmittance).abs().max()
    assert adaptive_err <= 1e-2 and fixed_err > adaptive_err, (
        f"adaptive {adaptive_err:.2e} with {int(out.evaluations.max())} samples vs fixed {fixed_err:.2e}")


def test_render_with_tolerance_reports_its_estimate_and_meets_it_on_a_smooth_medium():
    import torchvol as tv

    scene = {"image": {"width": 10, "height": 8}, "camera": {"eye": [0.3, 0.2, -3.0], "fov_y": 40},
             "lights": [{"direction": [0.3, 1.0, -0.4], "intensity": 2.0, "shadow": {"steps": 4}}],
             "volumes": [{"bounds": {"slab": {"y_min": -1.0, "y_max": 1.0}}, "sigma_t": 3.0,
                          "density": {"exponential": {"value": 1.0, "scale_height": 0.4}}}],
             "march": {"tolerance": 1e-3, "steps": 8, "max_distance": 8.0}}
    out = tv.render(scene)
    assert "error_estimate" in out.stats and out.stats["passes"][1] == "volume0.march"
    # the same pixel-centre rays (the reference level alone would supersample): march error only
    ref = tv.render(tv.load_scene(scene, {"march": {"quality": "reference", "steps": 4096, "max_distance": 8.0},
                                          "image.spp": 1}))
    assert (out.alpha - ref.alpha).abs().max() <= 1e-3
    assert ((out.radiance - ref.radiance).abs().max() / 2.0) <= 1e-3


@pytest.mark.parametrize("capped", [True, False])
def test_tolerance_holds_on_an_fbm_cloud_only_with_the_feature_cap(capped, monkeypatch):
    """Step doubling cannot see an fbm island that falls between its samples: with steps capped at
    half the finest octave's period (the field's `feature_size`) the tolerance holds; without the
    cap, at 8 steps per span, islands are stepped over and the error exceeds it."""
    import torchvol as tv
    from torchvol.fields.fbm import FbmField
    from torchvol.scene.presets import preset_dict

    scene = preset_dict("cloud-puff", width=24, height=16)
    scene["image"]["spp"] = 1
    if not capped:
        init = FbmField.__init__
        monkeypatch.setattr(FbmField, "__init__", lambda self, *a, **k: (init(self, *a, **k), setattr(self, "feature_size", None))[0])
    tolerance, light = 1e-3, 40.0  # the preset's sun intensity: radiance errors are relative to it
    out = tv.render(tv.load_scene(scene, {"march.tolerance": tolerance, "march.steps": 8}))
    ref = tv.render(tv.load_scene(scene, {"march.quality": "reference", "march.steps": 1024, "march.dither": "none",
                                          "march.min_transmittance": 1e-9}))
    err = max((out.alpha - ref.alpha).abs().max().item(), ((out.radiance - ref.radiance).abs().max() / light).item())
    if capped:
        assert err <= tolerance, f"error {err:.2e} over the tolerance {tolerance:g} (estimate {out.stats['error_estimate']:.2e})"
    else:
        assert err > tolerance, f"without the cap the error {err:.2e} should exceed {tolerance:g}: the test lost its teeth"


@functools.cache
def _cloud_puff(**overrides):
    """cloud-puff at 24×16, 1 spp, no early termination (its own error is not the march's), with
    `overrides` (key path -> value): (alpha, radiance) in float64."""
    import torchvol as tv
    from torchvol.scene.presets import preset_dict

    scene = preset_dict("cloud-puff", width=24, height=16)
    scene["image"]["spp"] = 1
    out = tv.render(tv.load_scene(scene, {"march.min_transmittance": 1e-12, **overrides}))
    return out.alpha.double(), out.radiance.double()


def test_tight_tolerance_holds_on_an_fbm_cloud_only_with_the_missed_depth(monkeypatch):
    """Under the feature cap, steps whose samples all read 0 still step over thin islands of
    clamped noise: step doubling estimates no error there. `missed_depth` (the quadratic through
    the signed samples) sees them: with it 1e-4 holds; without it the error is larger (how much
    depends on the CPU's last bits in the noise: 5.7e-5 with, 8.2e-5 without on one machine; over
    1e-4 without on another)."""
    from torchvol.volume import march as march_module

    tolerance, light = 1e-4, 40.0
    ref_alpha, ref_radiance = _cloud_puff(**{"march.quality": "reference", "march.steps": 2048, "march.dither": "none"})

    def error() -> tuple[float, tuple[int, int]]:
        alpha, radiance = _cloud_puff.__wrapped__(**{"march.tolerance": tolerance})
        alpha_err = (alpha - ref_alpha).abs()
        err = max(alpha_err.max().item(), ((radiance - ref_radiance).abs().max() / light).item())
        return err, divmod(int(alpha_err.flatten().argmax()), 24)

    seen, where = error()
    assert seen <= tolerance, f"error {seen:.2e} over {tolerance:g} (worst alpha at row, col {where})"
    monkeypatch.setattr(march_module, "missed_depth", lambda sigma_a, sigma_m, sigma_b, dt: torch.zeros_like(dt))
    blind, _ = error()
    assert blind > 1.2 * seen, (
        f"without missed_depth the error {blind:.2e} should be well above {seen:.2e} (with it): the test lost its teeth")


def test_missed_depth_is_the_depth_of_an_island_between_samples():
    """σ(s) = c − k(s − s₀)² on a step [0, 1]: a parabola the quadratic through the samples at 1/4,
    1/2, 3/4 reproduces exactly. Placed so that all three samples read σ < 0, its positive part
    (depth 4c^{3/2}/(3√k)) is what the step's samples miss; fully seen samples miss nothing."""
    from torchvol.volume.march import missed_depth

    c, k = torch.tensor([0.01, 0.04], dtype=torch.float64), torch.tensor([4.0, 25.0], dtype=torch.float64)
    s0 = 0.375  # between the first two samples

    def sigma(s):
        return c - k * (s - s0) ** 2

    got = missed_depth(sigma(0.25), sigma(0.5), sigma(0.75), torch.ones(2, dtype=torch.float64))
    exact = 4 * c**1.5 / (3 * k.sqrt())
    assert (sigma(0.25) < 0).all() and (sigma(0.5) < 0).all()
    assert torch.allclose(got, exact, rtol=1e-9), f"missed {got.tolist()} against {exact.tolist()}"
    flat = torch.full((2,), 3.0, dtype=torch.float64)
    assert (missed_depth(flat, flat, flat, torch.ones(2, dtype=torch.float64)) == 0).all()


@settings(max_examples=200, deadline=None)
@given(st.lists(st.sampled_from([0.0, 1.0, -1.0, 1e-6]) | st.floats(-50, 50), min_size=3, max_size=3))
def test_positive_part_integral_matches_a_dense_sum(coefficients):
    """Any quadratic, linear or constant (a = 0, b = 0 included): the root-cut integral equals a
    dense midpoint sum of max(q, 0) over [−2, 2]."""
    from torchvol.volume.march import positive_part_integral

    c, b, a = (torch.tensor([v], dtype=torch.float64) for v in coefficients)
    x = torch.linspace(-2.0, 2.0, 200_001, dtype=torch.float64)
    x = 0.5 * (x[1:] + x[:-1])
    dense = (c + b * x + a * x * x).clamp_min(0.0).sum() * (4.0 / x.numel())
    got = positive_part_integral(c, b, a, -2.0, 2.0)
    assert torch.isfinite(got).all()
    assert abs(float(got) - float(dense)) <= 1e-6 * (1.0 + abs(float(dense))), f"{float(got)} against {float(dense)}"


def test_steps_rounded_together_far_along_a_ray_stay_finite(one_thread):
    # the production cloudscape at the error-controlled march: far along a ray a step near its
    # floor rounds its three abscissae together in float32; the light's curvature was 0/0 there,
    # the error and the next step NaN, the depth NaN (found by the fuzz, tools/fuzz.py)
    s = tv.load_scene("cloudscape", {"image.width": 8, "image.height": 5, "march.quality": "draft",
                                     "march.tolerance": 1e-3, "march.steps": 2})
    out = tv.render(s)
    for name, value in {"radiance": out.radiance, "depth": out.depth, "alpha": out.alpha}.items():
        assert bool(torch.isfinite(value).all()), name
