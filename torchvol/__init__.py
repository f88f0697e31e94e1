"""torchvol: batched PyTorch renderer of volumes and voxels for synthetic training data."""

__version__ = "0.1.0"
