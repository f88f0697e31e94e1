"""Elementwise maths whose result does not depend on where an element sits in its tensor.

torch's CPU kernels run a vectorised body and a scalar tail; for most functions (exp, log, sin,
sqrt, ...) both round alike, but not for `pow` with a non-integer exponent (nor `atan2`): the same
value then differs by an ulp between a render alone and in a batch, or between chunk sizes. The
renderer promises bitwise-equal results for those, so it computes powers here."""

from __future__ import annotations

import torch
from torch import Tensor


def pow_(x: Tensor, y: Tensor | float) -> Tensor:
    """x ** y for x ≥ 0 and y > 0, as exp(y · ln x) (0 at x = 0). Shapes broadcast."""
    return torch.exp(y * torch.log(x))
