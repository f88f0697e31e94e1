"""The package's layers, bottom first: the one table of what may import what.

A module may import from its own top-level package or module and from any entry of a lower tier;
entries of one tier are siblings and import none of each other. `tests/test_layers.py` walks every
import of the package (function-local ones too) and fails on an import that points up or sideways,
and on any import cycle. docs/ARCHITECTURE.md draws the same table.
"""

LAYERS: tuple[tuple[str, ...], ...] = (
    ("ops", "version", "layers"),  # tensor helpers; the version; this table
    ("schema",),  # validation, key paths, strict models and batch roles, registries, the stacked batch
    ("runtime",),  # threads, heap, the compile setting, progress bars, process tuning
    ("noise",),  # lattice noises and fbm, their arithmetic-hash twins, noise textures
    ("geometry",),  # camera and rays, intersections, bounds, SDFs, per-ray sampling, surface hits
    ("fields", "light"),  # densities | lights, skies, phase functions, the atmosphere
    ("volume", "voxel", "terrain", "post"),  # the techniques: media, voxel surfaces, terrain, image effects
    ("scene",),  # the scene model, quality levels, presets, loading
    ("renderer",),  # plan, executor, labels, AOVs, stats, accumulation
    ("dataset",),  # recipes, distributions, views, sequences, labels, file codec, Datasets, generation
    ("measure",),  # references, sweeps, figures, benchmarks, GLSL and Mitsuba harnesses
    ("cli",),  # the command line
)

__all__ = ["LAYERS"]
