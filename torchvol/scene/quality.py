"""Quality levels: what `march.quality` (draft, default, high, reference) sets where the scene
does not say, and the march settings of a scene."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch

from ..volume.march import MarchSettings, StepRule
from .model import March, Scene, VoxelShadow

Quality = Literal["draft", "default", "high", "reference"]


@dataclass(frozen=True)
class Level:
    """What a named quality level sets where the scene does not say (explicit keys win)."""

    steps: int  # volume march steps (count placement)
    min_transmittance: float  # rays stop below it
    dtype: torch.dtype
    shadow_steps: int  # a light's `shadow.steps`
    voxel_shadow_steps: int  # `voxels.shadow.steps` (DDA step limit of a shadow ray)
    spp: int  # `image.spp`: the reference integrates each pixel, so aliasing counts as error
    voxel_max_steps: int  # `voxels.max_steps`: a primary DDA ray stopped by it is a hole in the image
    fog_shadow_steps: int  # `voxels.fog.shadow_steps`
    atmosphere_steps: tuple[int, int]  # `sky.atmosphere.steps`, `.light_steps` (and `atmosphere.`'s)


# Count placement, frostbite, hashed dither (none at reference) at every level. `default` equals
# the schema's former fixed defaults (shadow 16, voxel shadow 32, spp 1): scenes that relied on them
# render unchanged. `high` takes the reference's spp: the same seeded sub-samples, so what is left
# of its error is the march's. The primary steps of `high` and `reference` are what their shadow
# steps let count: twice and four times as many bought no smaller error (docs/QUALITY.md).
QUALITY: dict[str, Level] = {
    "draft": Level(32, 1e-2, torch.float32, shadow_steps=8, voxel_shadow_steps=16, spp=1,
                   voxel_max_steps=256, fog_shadow_steps=8, atmosphere_steps=(8, 4)),
    "default": Level(128, 1e-4, torch.float32, shadow_steps=16, voxel_shadow_steps=32, spp=1,
                     voxel_max_steps=256, fog_shadow_steps=16, atmosphere_steps=(16, 8)),
    "high": Level(192, 1e-5, torch.float32, shadow_steps=32, voxel_shadow_steps=128, spp=4,
                  voxel_max_steps=1024, fog_shadow_steps=32, atmosphere_steps=(32, 16)),
    "reference": Level(512, 1e-12, torch.float64, shadow_steps=64, voxel_shadow_steps=1024, spp=4,
                       voxel_max_steps=4096, fog_shadow_steps=64, atmosphere_steps=(64, 32)),
}


PATH_STAND_INS = ("multiple_scattering", "ambient", "bloom")  # a volume's approximations of what paths trace


def at_level(scene: Scene) -> Scene:
    """The scene with every key its quality level decides filled in (`image.spp`, lights'
    `shadow.steps`, `voxels.shadow.steps`, `voxels.max_steps`, `voxels.fog.shadow_steps`,
    `sky.atmosphere.steps` and `.light_steps`, `atmosphere.steps` and `.light_steps`), and with
    `[path]` without the march's stand-ins for the orders it traces (`_without_stand_ins`);
    idempotent. Everything after this sees plain ints."""
    level = QUALITY[scene.march.quality]
    dropped = _without_stand_ins(scene)  # first: the levels fill in what it adds (the voxels' shadow)
    scene = scene.model_copy(update=dropped) if dropped else scene
    update: dict = {}
    if scene.image.spp is None:
        update["image"] = scene.image.model_copy(update={"spp": level.spp})
    if any(li.shadow is not None and li.shadow.steps is None for li in scene.lights):
        update["lights"] = [
            li if li.shadow is None or li.shadow.steps is not None
            else li.model_copy(update={"shadow": li.shadow.model_copy(update={"steps": level.shadow_steps})})
            for li in scene.lights
        ]
    vx = scene.voxels
    if vx is not None:
        fill: dict = {}
        if vx.shadow is not None and vx.shadow.steps is None:
            fill["shadow"] = vx.shadow.model_copy(update={"steps": level.voxel_shadow_steps})
        if vx.max_steps is None:
            fill["max_steps"] = level.voxel_max_steps
        if vx.fog is not None and vx.fog.shadow_steps is None:
            fill["fog"] = vx.fog.model_copy(update={"shadow_steps": level.fog_shadow_steps})
        if fill:
            update["voxels"] = vx.model_copy(update=fill)
    atm = getattr(scene.sky, "atmosphere", None)
    if atm is not None and (atm.steps is None or atm.light_steps is None):
        update["sky"] = scene.sky.model_copy(update={"atmosphere": _atmosphere_steps(atm, level)})
    if scene.atmosphere is not None and (scene.atmosphere.steps is None or scene.atmosphere.light_steps is None):
        update["atmosphere"] = _atmosphere_steps(scene.atmosphere, level)
    return scene.model_copy(update=update) if update else scene


def _without_stand_ins(scene: Scene) -> dict:
    """With `[path]` the paths trace the orders past the first: the march's stand-ins for them (a
    volume's octaves, sky ambient and bloom, the terrain's ambient, the voxels' ambient, AO, GI,
    mirror reflections and face tones) are dropped, so they cost nothing and `single = "march"` adds the paths to the
    plain single scattering (the voxels' faces shadowed, as the paths' are). -> the update."""
    if scene.path is None:
        return {}
    update: dict = {}
    if any(getattr(v, key, None) is not None for v in scene.volumes for key in PATH_STAND_INS):
        update["volumes"] = [v.model_copy(update=dict.fromkeys(PATH_STAND_INS)) for v in scene.volumes]
    if scene.terrain is not None and any(scene.terrain.ambient):
        update["terrain"] = scene.terrain.model_copy(update={"ambient": (0.0, 0.0, 0.0)})
    if scene.voxels is not None:  # Lambert faces, shadowed as the paths' are
        vx = scene.voxels
        update["voxels"] = vx.model_copy(update={"ambient": (0.0, 0.0, 0.0), "ao": None, "gi": None, "reflections": None,
                                                 "face_tones": (1.0, 1.0, 1.0),
                                                 "shadow": VoxelShadow() if vx.shadow is None else vx.shadow})
    return update


def _atmosphere_steps(layer, level: Level):
    """An air layer (the sky's or the medium's) with the level's steps where it gives none."""
    steps, light_steps = level.atmosphere_steps
    return layer.model_copy(update={"steps": steps if layer.steps is None else layer.steps,
                                    "light_steps": light_steps if layer.light_steps is None else layer.light_steps})


def march_settings(march: March) -> MarchSettings:
    """The march settings a scene's `march` table comes to: its explicit keys, the rest from its
    quality level."""
    level = QUALITY[march.quality]
    steps, min_t, dtype = level.steps, level.min_transmittance, level.dtype
    reference = march.quality == "reference"
    placement = march.placement or ("size" if march.step_size is not None and march.steps is None else "count")
    if placement == "size" and march.steps is None:
        steps = 1_000_000  # bounded by the exit, not by a count
    rule = StepRule(
        placement=placement,
        steps=march.steps if march.steps is not None else steps,
        step_size=march.step_size if march.step_size is not None else 0.05,
        step_growth=march.step_growth if march.step_growth is not None else 0.0,
    )
    return MarchSettings(
        rule=rule,
        integrator=march.integrator or "frostbite",
        dither=march.dither or ("none" if reference else "hash"),
        dither_scale=march.dither_scale if march.dither_scale is not None else 1.0,
        max_distance=march.max_distance,
        min_transmittance=march.min_transmittance if march.min_transmittance is not None else min_t,
        density_threshold=march.density_threshold if march.density_threshold is not None else 0.0,
        lod_scale=march.lod.scale if march.lod is not None else None,
        closed_form=march.closed_form,
        depth_threshold=march.depth_threshold,
        dtype=dtype,
        tolerance=march.tolerance,
    )
