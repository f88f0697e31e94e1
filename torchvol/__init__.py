"""torchvol: batched PyTorch renderer of volumes and voxels for synthetic training data.

Importing the package imports no torch and changes nothing in the process (no environment
variable, allocator or thread setting): each public name loads its module on first use (PEP 562).
The tuning that helps a rendering process is one call, `tune_process` (torchvol.runtime.process).
"""

import importlib

from .version import __version__ as __version__  # the one version, below every layer

# each public name -> the module that defines it, imported on first access
PUBLIC = {
    "Camera": "geometry.camera",
    "Rays": "geometry.camera",
    "FolderDataset": "dataset.datasets",
    "SceneDataset": "dataset.datasets",
    "Recipe": "dataset.recipe",
    "RenderOutput": "renderer.executor",
    "render": "renderer.executor",
    "Scene": "scene.model",
    "load_scene": "scene.model",
    "preset": "scene.model",
    "preset_names": "scene.model",
    "SceneError": "schema.validate",
    "tune_process": "runtime.process",
}
__all__ = sorted(PUBLIC)


def __getattr__(name: str):
    if name not in PUBLIC:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{PUBLIC[name]}", __name__), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(PUBLIC))
