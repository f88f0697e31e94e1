"""The volume as a label (`[dataset] volume_label = { resolution = N }`): a scene's extinction on a grid.

`extinction` (N, N, N) float32 holds σ_t · density summed over the scene's volumes, sampled at the
centres of the N³ cells of `extinction_box` (2, 3) float32 (min and max corners: the union of the
volumes' bounding boxes). Index [k, j, i] is the centre of cell (i, j, k), i along x, j along y, k
along z: the convention of grid media (`fields/grid.py`), so the label renders back as
`density = { grid = { data = extinction } }` with `sigma_t = 1` over `bounds = { box = ... }`.

The densities come from the renderer's own fields (`renderer.executor.RenderContext`: the field classes, the
`edge` fade, the scene's `time`, the quality level's dtype), evaluated at full detail (no `march.lod`)
and masked to each volume's bounds, as the march sees them. A volume with unbounded bounds (a slab)
has no box: refused.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..schema.validate import fail
from ..volume.context import VolumeContext

# Grid points evaluated per field call: bounds the memory of large resolutions.
CHUNK_POINTS = 1 << 16


def cell_centres(box_min: Tensor, box_max: Tensor, n: int) -> Tensor:
    """Centres of the n³ cells of the box (`box_min`, `box_max` [3]) -> [n³, 3] in [k, j, i] order."""
    u = (torch.arange(n, dtype=box_min.dtype) + 0.5) / n
    axes = [box_min[a] + (box_max[a] - box_min[a]) * u for a in range(3)]  # along x, y, z
    z, y, x = torch.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    return torch.stack([x, y, z], dim=-1).reshape(-1, 3)


def check_scene(scene, resolution: int) -> None:
    """Refuse (naming `dataset.volume_label`) a scene whose extinction has no box to grid: no
    volumes, or a volume with unbounded bounds (a slab)."""
    from ..geometry.bounds import BOUNDS

    if not scene.volumes:
        fail("dataset.volume_label", {"resolution": resolution}, "the scene has no volumes to label")
    for i, vol in enumerate(scene.volumes):
        if BOUNDS[vol.bounds.kind].caps.get("aabb") is None:
            fail("dataset.volume_label", {"resolution": resolution},
                 f"volumes[{i}] has {vol.bounds.kind} bounds, which have no box to grid; "
                 "give every volume a box, sphere or shell")


def extinction_grid(scene, resolution: int) -> tuple[Tensor, Tensor]:
    """(`extinction` (N, N, N) float32 [k, j, i], `extinction_box` (2, 3) float32) of one scene
    (a Scene, dict, path or preset name) at its `time`, from a render context of its own (the
    dataset takes the label from its render's context instead: `extinction_of`)."""
    from ..renderer.executor import RenderContext
    from ..renderer.plan import make_plan
    from ..renderer.prepare import prepare
    from ..schema.batch import stack

    batch = prepare(scene)
    check_scene(batch.scenes[0], resolution)
    plan = make_plan(stack(batch.scenes, dtype=torch.float64))
    ctx = RenderContext(stack(batch.scenes, dtype=plan.dtype), plan, seeds=[0], device="cpu")
    return extinction_of(ctx, 0, resolution)


def extinction_of(ctx: VolumeContext, b: int, resolution: int) -> tuple[Tensor, Tensor]:
    """`extinction_grid` of scene `b` of a render's context `ctx` (`RenderContext`: its volumes'
    fields, bounds and σ_t, in its dtype): (N, N, N) float32 [k, j, i] and its box (2, 3) float32."""
    from ..schema.batch import take

    boxes = torch.stack([torch.cat([c[b:b + 1] for c in vol.bounds.caps["aabb"](vol.params.bounds.value)])
                         for vol in ctx.volumes])  # (volumes, 2, 3)
    box = torch.stack([boxes[:, 0].amin(0), boxes[:, 1].amax(0)])  # the union: (2, 3) min, max
    points = cell_centres(box[0], box[1], resolution)
    sigma = torch.zeros(points.shape[0], dtype=ctx.dtype)
    for first in range(0, points.shape[0], CHUNK_POINTS):
        p = points[first:first + CHUNK_POINTS]
        s = torch.full((p.shape[0],), b, dtype=torch.long)
        for vol in ctx.volumes:
            inside = vol.bounds.caps["depth"](vol.params.bounds.value, p, s) >= 0
            value = take(vol.params.sigma_t, s) * vol.field(p, s)
            sigma[first:first + CHUNK_POINTS] += torch.where(inside, value, torch.zeros_like(value))
    return sigma.reshape(resolution, resolution, resolution).float(), box.float()


def grid_scene(scene, extinction: Tensor, box: Tensor):
    """`scene` with its volumes replaced by the label rendered back: one grid medium of density
    `extinction` (N, N, N) [k, j, i] over the box `box` (2, 3), σ_t = 1, with volumes[0]'s albedo,
    phase and shading; camera, lights and sky as they are. Its alpha reproduces the scene's to
    within the grid's resolution error (docs/DATASETS.md)."""
    from ..scene.model import load_scene, validate_scene

    data = load_scene(scene).model_dump(exclude_unset=True)
    first = data["volumes"][0]
    data["volumes"] = [{
        "bounds": {"box": {"min": box[0].tolist(), "max": box[1].tolist()}},
        "density": {"grid": {"data": extinction.numpy()}},
        "sigma_t": 1.0,
        **{key: first[key] for key in ("albedo", "phase", "shading") if key in first},
    }]
    return validate_scene(data)
