"""The shader look's start dither: a hashed dither moves a ray's first sample by a fraction of a
step (the seeds' t += STEP_SIZE·hash), the template's sin dither by its absolute scale."""

from __future__ import annotations

import pytest
import torch

from torchvol.volume.march import StepRule, march


def first_sample(dither: float, unit: str, rule: StepRule) -> float:
    seen = []

    def medium(ids, t, dt):
        seen.append(t.clone())
        return torch.zeros_like(t), torch.zeros(t.shape[0], 3, dtype=t.dtype)

    t0, t1 = torch.tensor([2.0], dtype=torch.float64), torch.tensor([6.0], dtype=torch.float64)
    march(t0, t1, torch.tensor([True]), medium, rule=rule, integrator="alpha", semantics="shader",
          dither=torch.tensor([dither], dtype=torch.float64), dither_unit=unit)
    return float(seen[0][0])


@pytest.mark.parametrize("rule, step", [(StepRule("count", 40), 0.1), (StepRule("size", 100, step_size=0.05), 0.05),
                                        (StepRule("adaptive", 100, step_size=0.05, step_growth=0.1), 0.2)])
def test_a_hashed_dither_is_a_fraction_of_the_first_step(rule, step):
    assert first_sample(0.9, "step", rule) == pytest.approx(2.0 + 0.9 * step, abs=1e-12)
    assert first_sample(0.9, "absolute", rule) == pytest.approx(2.9, abs=1e-12)  # the template's scale is in world units
