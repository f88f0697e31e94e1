"""Measuring: the reference ladder, sweeps, figures, accuracy and speed benchmarks, and the GLSL
(Mesa llvmpipe) and Mitsuba 3 harnesses the parity tests and benchmarks use."""
