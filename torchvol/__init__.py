"""torchvol: batched PyTorch renderer of volumes and voxels for synthetic training data."""

import os

# OpenMP threads sleep between parallel regions instead of spinning: a render's thousands of small
# ops otherwise spin against any other busy process (docs/SPEED.md, "One busy competitor"). libgomp
# reads this once, when torch loads: it holds where torchvol is imported first (the CLI) and in
# every process started later (generator and DataLoader workers). A user's own setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from .runtime import heap

# freed tensors stay in the heap for the next march step's: no page faults at every step
# (torchvol/heap.py); in every process that imports torchvol, unless the environment tunes malloc
heap.keep_freed_memory()

from .geometry.camera import Camera, Rays
from .dataset.datasets import FolderDataset, SceneDataset
from .dataset.recipe import Recipe
from .renderer.executor import RenderOutput, render
from .scene.model import Scene, load_scene, preset, preset_names
from .schema.validate import SceneError

from .version import __version__  # noqa: E402
__all__ = ["Camera", "FolderDataset", "Recipe", "SceneDataset", "Rays", "RenderOutput", "Scene", "SceneError", "load_scene", "preset", "preset_names", "render"]
