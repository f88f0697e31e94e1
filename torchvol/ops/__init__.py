"""Tensor helpers below every technique: bitwise-stable powers, row gathers, grid sampling."""
