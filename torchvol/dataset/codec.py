"""The file codec of one sample: the named files a generated dataset stores, and back.

`encode_sample` turns a sample (`datasets.py`: image (3,H,W), depth (1,H,W), ...) into files: PNG
for image and alpha, exact float32 .npy for depth, compressed .npz for AOVs (`AOV_STORAGE`), per
view or frame with its index (`views.py`), the volume label's .npy; `sample_record` its JSON record.
`decode_file` reads one file back. The generator and FolderDataset share them so the two stay in
step; `CONVENTIONS` states them in meta.json.
"""

from __future__ import annotations

import io
import zipfile
from typing import Mapping, Sequence

import numpy as np
import torch

from .views import encode_views, view_count

# The conventions a generated dataset states in meta.json (DESIGN.md, Conventions).
CONVENTIONS = {
    "image": "8-bit sRGB-encoded PNG of the display-referred image in [0, 1] (row 0 = top)",
    "depth": "planar z along the camera's forward axis (not ray distance), float32 .npy of shape (H, W), "
             "world units; 0 where nothing was hit (invalid)",
    "alpha": "8-bit PNG of 1 - transmittance of the whole ray",
    "aovs": "compressed .npz holding one array named after the AOV, shape (C, H, W): float32 (lossless) for "
            "normal, ao, shadow, distance, depth_median, radiance, optical_thickness, alpha_volumes and "
            "sun_visibility; uint8 for material ids; uint16 for instance ids; float16 for uv "
            "(face coordinates in [0, 1], within 2.5e-4)",
    "units": "world units; angles in degrees; right-handed world, y up",
    "camera": "OpenCV/kornia: camera axes x right, y down, z forward; K in pixels with pixel centres at "
              "integer coordinates (centred principal point cx = W/2 - 0.5); world_to_camera maps world "
              "points to camera coordinates",
    "invalid_depth": 0.0,
}


def sample_record(item: Mapping, files: Mapping[str, str]) -> dict:
    """The manifest record of one sample (JSON-safe)."""
    return {
        "index": item["index"],
        "seed": item["seed"],
        "files": dict(files),
        "K": item["K"].tolist(),
        "world_to_camera": item["world_to_camera"].tolist(),
        "params": item["params"],
    }


# zlib's level for the PNGs and .npz files: 1, not the libraries' 6. A generator's worker spends it
# on every sample: a 128² voxel-pbr sample's files took 5.8 ms to encode at level 6 (its render ~17),
# 3.4 ms at level 1, for 7% more bytes (docs/DATASETS.md)
DEFLATE_LEVEL = 1


def png_bytes(array: np.ndarray) -> bytes:
    """An 8-bit PNG of `array` (H, W) or (H, W, 3) uint8."""
    from PIL import Image  # loaded when files are written, not by `import torchvol`

    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG", compress_level=DEFLATE_LEVEL)
    return buf.getvalue()


def npy_bytes(array: np.ndarray) -> bytes:
    """An exact float32 .npy of `array` (any shape)."""
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(array, dtype=np.float32), allow_pickle=False)
    return buf.getvalue()


# How each AOV is stored, in a compressed .npz: lossless float32 (face normals, AO levels and hard
# shadows take few distinct values: they compress well, docs/DATASETS.md), material ids as bytes
# (at most 255 materials), and uv in float16: face coordinates in [0, 1] to within 2^-12 of a face.
# instance ids (torchvol.renderer.labels) as uint16: volumes and materials together stay far below 65536
AOV_STORAGE = {"material": np.uint8, "uv": np.float16, "instance": np.uint16, "flow_valid": np.uint8}


def npz_bytes(name: str, array: np.ndarray) -> bytes:
    """A compressed .npz holding `array` (any shape) as `name`, in the dtype AOV_STORAGE gives `name`
    (float32 else): np.savez_compressed's format with a fixed timestamp, so the same array gives the
    same bytes."""
    member = io.BytesIO()
    np.save(member, np.ascontiguousarray(array, dtype=AOV_STORAGE.get(name, np.float32)), allow_pickle=False)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as archive:
        info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
        info.compress_type = zipfile.ZIP_DEFLATED
        archive.writestr(info, member.getvalue(), compresslevel=DEFLATE_LEVEL)
    return buf.getvalue()


def to_uint8(x: torch.Tensor) -> np.ndarray:
    """`x` in [0, 1] (any shape) as 8-bit levels, rounded to nearest (values outside clipped)."""
    return np.round(np.clip(x.numpy(), 0.0, 1.0) * 255.0).astype(np.uint8)


def encode_sample(item: Mapping, aovs: Sequence[str]) -> dict[str, bytes]:
    """{suffix: bytes}: image.png, depth.npy (H, W), alpha.png, one <aov>.npz each (C, H, W); with
    several views each view's as image.{v}.png, ... (`views.py`); with the volume label
    extinction.npy (N, N, N) and extinction_box.npy (2, 3)."""
    if view_count(item) is not None:
        return {**encode_views(item, lambda one: encode_sample(one, aovs)), **label_files(item)}
    files = {
        "image.png": png_bytes(to_uint8(item["image"].permute(1, 2, 0))),
        "depth.npy": npy_bytes(item["depth"][0].numpy()),
        "alpha.png": png_bytes(to_uint8(item["alpha"][0])),
    }
    for name in aovs:
        files[f"{name}.npz"] = npz_bytes(name, item[name].numpy())
    return {**files, **label_files(item)}


def label_files(item: Mapping) -> dict[str, bytes]:
    """A sample's volume-label files (`volume_label.py`): extinction.npy (N, N, N), extinction_box.npy
    (2, 3); none without the label."""
    if "extinction" not in item:
        return {}
    return {"extinction.npy": npy_bytes(item["extinction"].numpy()),
            "extinction_box.npy": npy_bytes(item["extinction_box"].numpy())}


def decode_file(suffix: str, data: bytes) -> torch.Tensor:
    """Inverse of encode_sample for one file: image (3,H,W), alpha/depth (1,H,W), AOV (C,H,W)."""
    if suffix.endswith(".png"):
        from PIL import Image

        array = np.asarray(Image.open(io.BytesIO(data)))
        x = torch.from_numpy(array.astype(np.float32) / 255.0)
        return x.permute(2, 0, 1).contiguous() if x.ndim == 3 else x[None]
    if suffix.endswith(".npz"):
        with np.load(io.BytesIO(data), allow_pickle=False) as stored:
            return torch.from_numpy(stored[suffix.split(".")[0]].astype(np.float32))
    array = torch.from_numpy(np.load(io.BytesIO(data), allow_pickle=False))
    return array[None] if suffix.split(".")[0] == "depth" else array  # depth.npy, depth.{v}.npy
