"""A batch as the renderer takes it, prepared once at the boundary.

`prepare` loads and validates each scene, fills in what its quality level decides (`at_level`),
checks that the scenes share one structure and refuses settings that cannot render together; the
`Batch` it returns carries its structure key. `render` takes a `Batch` as it is (no second load,
level or check); `group` splits any list of scenes into such batches, levelling and keying each
scene once (the dataset renders a recipe's draws this way). Nothing later refuses user input.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

from ..scene.model import Scene, load_scene
from ..scene.quality import at_level, march_settings
from ..schema.batch import check_same_structure, structure_key
from ..schema.validate import fail


@dataclass(frozen=True)
class Batch:
    """B scenes of one structure, validated and at their quality level (`scenes`), and the
    structure key they share (`key`, `schema.batch.structure_key`)."""

    scenes: tuple[Scene, ...]
    key: tuple

    def __len__(self) -> int:
        return len(self.scenes)


def check_settings(scene: Scene) -> None:
    """Refuses a levelled scene's settings that cannot render together (the accumulation's passes
    need a hashed dither or sub-pixel jitter to differ)."""
    if scene.image.passes > 1 and march_settings(scene.march).dither != "hash" and scene.image.spp == 1:
        fail("image.passes", scene.image.passes, "passes differ by their hashed march dither or sub-pixel jitter: set "
             "march.dither = 'hash' or image.spp > 1")


def prepare(scene: Any) -> Batch:
    """`scene` (a Scene, dict, .toml path or preset name, a list of those, or a `Batch`, returned as
    it is) as a `Batch`; raises ValueError naming the key of whatever is refused."""
    if isinstance(scene, Batch):
        return scene
    scenes = [at_level(load_scene(s)) for s in (scene if isinstance(scene, (list, tuple)) else [scene])]
    if not scenes:
        fail("scene", scene, "expected at least one scene")
    check_same_structure(scenes)  # (a shared setting is the same in every scene)
    check_settings(scenes[0])
    return Batch(tuple(scenes), structure_key(scenes[0]))


def group(scenes: Sequence[Scene]) -> list[tuple[list[int], Batch]]:
    """`scenes` (validated Scenes of any structures) as batches of one structure each, in the order
    their structures first appear: [(positions in `scenes`, Batch)]. Each scene is levelled and
    keyed once."""
    levelled = [at_level(s) for s in scenes]
    groups: dict[tuple, list[int]] = {}
    for i, scene in enumerate(levelled):
        groups.setdefault(structure_key(scene), []).append(i)
    out = []
    for key, positions in groups.items():
        members = [levelled[i] for i in positions]
        check_settings(members[0])  # one key: one structure, shared settings equal
        out.append((positions, Batch(tuple(members), key)))
    return out


__all__ = ["Batch", "check_settings", "group", "prepare"]
