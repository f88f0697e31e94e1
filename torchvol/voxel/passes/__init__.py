"""The voxel surface's passes, each a class holding one technique, assembled by
`voxel/surface.py: VoxelSurface`: `shading` (a hit's `ShadingPoint`, `point.py`; AO; its lit
colour), `direct` (the lights and their shadow rays), `secondary` (secondary rays and mirror
reflections), `water`, `paths` and `cones` (the two GI methods), `fog` (fog and glow, gathered
along the DDA) and `rounded` (rounded voxels). All trace through one `voxel/tracer.py: VoxelTracer`."""
