"""Noise functions: lattice noises and fbm (`lattice`), the arithmetic-hash twins (`fast`), tiled
noise textures (`tiles`)."""
