"""Light: light sources, skies, phase functions and the Rayleigh + Mie atmosphere."""
