"""Phase functions (volume/phase.py), the shadow march (volume/shadow.py) and the derivative light
(volume/shader_look.py)."""

import math

import pytest
import torch
from conftest import assert_close

from torchvol.light import phase
from torchvol.volume import shader_look, shadow


def sphere_integral(phase, n=2_000_001):
    """∫ p(cos θ) dω = 2π ∫_{-1}^{1} p(μ) dμ by the trapezoid rule on a fine float64 grid."""
    mu = torch.linspace(-1.0, 1.0, n, dtype=torch.float64)
    return 2 * math.pi * float(torch.trapezoid(phase(mu), mu))


@pytest.mark.parametrize("g", [-0.9, -0.3, 0.0, 0.5, 0.85])
def test_phase_functions_are_normalised(g):
    for name, fn in [
        ("hg", lambda mu: phase.henyey_greenstein(mu, g)),
        ("mie", lambda mu: phase.mie_cornette_shanks(mu, g)),
        ("dual", lambda mu: phase.dual_henyey_greenstein(mu, g, -0.2, 0.3)),
        ("rayleigh", phase.rayleigh),
        ("isotropic", phase.isotropic),
    ]:
        total = sphere_integral(fn)
        assert abs(total - 1.0) < 1e-6, f"{name} g={g}: ∫p dω = {total}"


def test_hg_forward_peak_looks_towards_the_sun():
    """cos θ = dot(ray, sun) with the sun direction towards the sun: g > 0 peaks at cos θ = 1."""
    mu = torch.linspace(-1, 1, 201, dtype=torch.float64)
    assert phase.henyey_greenstein(mu, 0.8).argmax() == 200
    assert phase.henyey_greenstein(mu, -0.8).argmax() == 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("g", [-0.999, 0.999, -0.99999, 0.99999])
def test_hg_stays_finite_near_g_one(dtype, g):
    mu = torch.tensor([-1.0, -0.5, 0.0, 0.999, 1.0], dtype=dtype)
    value = phase.henyey_greenstein(mu, g)
    assert torch.isfinite(value).all() and (value > 0).all(), value
    # the exact value at the peak: (1 − g²)/(4π (1 − |g|)³) = (1 + |g|)/(4π (1 − |g|)²)
    peak = value[-1] if g > 0 else value[0]
    a = abs(float(torch.tensor(g, dtype=dtype)))  # g as the dtype holds it
    expected = (1 + a) / (4 * math.pi * (1 - a) ** 2)
    assert abs(float(peak) / expected - 1) < (1e-3 if dtype == torch.float32 else 1e-9)
    # a dot product of unit vectors rounds past ±1 (a direction drawn about another at cos −1):
    # the peak's value, not the infinity a negative base gave at |g| near 1
    ulp = float(torch.finfo(dtype).eps)
    past = phase.henyey_greenstein(torch.tensor([-1.0 - 2 * ulp, 1.0 + 2 * ulp], dtype=dtype), g)
    assert torch.equal(past, value[[0, -1]]), past


@pytest.mark.parametrize("growth,first", [(1.0, None), (1.3, None), (1.3, 0.05), (2.0, 0.5)])
def test_shadow_segments_cover_the_exit_exactly(growth, first):
    exit_t = torch.tensor([0.0, 0.3, 2.0, 17.0], dtype=torch.float64)
    mid, length = shadow.shadow_distances(exit_t, steps=8, growth=growth, first_step=first)
    assert (length >= 0).all() and (mid <= exit_t[:, None]).all()
    if first is None:  # fitted to the exit: the segments tile [0, exit]
        assert_close(length.sum(1), exit_t, what="covered length")
    else:  # cut at the exit: never beyond it
        assert (length.sum(1) <= exit_t + 1e-12).all()


def test_shadow_transmittance_of_a_homogeneous_medium_is_exact():
    points = torch.zeros(5, 3, dtype=torch.float64)
    sun = torch.tensor([[0.0, 1.0, 0.0]] * 5, dtype=torch.float64)
    exit_t = torch.tensor([0.0, 0.1, 1.0, 3.0, 50.0], dtype=torch.float64)
    sigma = 2.5
    t = shadow.shadow_transmittance(points, sun, exit_t, lambda q, owner: torch.full_like(q[:, 0], sigma), steps=5, growth=1.4)
    assert_close(t, torch.exp(-sigma * exit_t), what="shadow transmittance")


def test_derivative_light_is_the_seeds_formula():
    d = torch.tensor([0.5, 0.5, 0.2, 0.9])
    ahead = torch.tensor([0.2, 0.9, 0.2, 0.0])
    assert_close(shader_look.derivative_light(d, ahead, scale=0.6), torch.tensor([0.5, 0.0, 0.0, 1.0]), atol=1e-7)
