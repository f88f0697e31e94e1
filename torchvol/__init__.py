"""torchvol: batched PyTorch renderer of volumes and voxels for synthetic training data."""

from .camera import Camera, Rays
from .data import FolderDataset, SceneDataset
from .recipe import Recipe
from .render import RenderOutput, render
from .scene import Scene, load_scene, preset, preset_names
from .validate import SceneError

__version__ = "0.1.0"
__all__ = ["Camera", "FolderDataset", "Recipe", "SceneDataset", "Rays", "RenderOutput", "Scene", "SceneError", "load_scene", "preset", "preset_names", "render"]
