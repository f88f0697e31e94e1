"""The noise-debiased RMSE against a converged render (`debiased_relative_rmse`), on synthetic passes
whose converged image is known: no Mitsuba needed."""

import numpy as np
import pytest

from torchvol.measure.mitsuba import debiased_relative_rmse, relative_rmse


@pytest.mark.parametrize("bias", [0.0, 1e-3, 5e-3])
def test_debiased_rmse_finds_the_difference_under_the_noise(bias):
    rng = np.random.default_rng(7)
    converged = np.repeat(rng.uniform(0.5, 1.5, size=(64, 64, 1)), 3, axis=2)  # a grey image
    image = converged * (1.0 + bias * rng.standard_normal((64, 64, 1)))
    noise = 0.02 * converged.mean()  # each pass: 2% noise, 16 passes, so the mean's noise (0.5%) hides the bias
    passes = converged + noise * np.repeat(rng.standard_normal((16, 64, 64, 1)), 3, axis=3)
    truth = relative_rmse(image, converged)
    got = debiased_relative_rmse(image, passes)
    assert got["low"] <= truth <= got["high"], f"true {truth:.3e} outside [{got['low']:.3e}, {got['high']:.3e}] (estimate {got['rmse']:.3e})"
    # the plain RMSE carries the mean's noise on top of the difference (squares add)
    assert got["raw"] ** 2 > truth**2 + 0.5 * got["noise"] ** 2, f"plain {got['raw']:.3e}, true {truth:.3e}, noise {got['noise']:.3e}"
    assert got["high"] - got["low"] < max(0.3 * truth, 2e-3), f"bounds too wide: [{got['low']:.3e}, {got['high']:.3e}]"
    assert abs(got["noise"] - noise / np.sqrt(16) / np.sqrt((converged**2).mean())) < 0.05 * got["noise"]
