"""`voxels.materials`: a colour or a table { color, emission }. The colour
form renders as before (a table of that colour is the same scene); emission is the radiance
leaving a face, added to its reflected light, and planned only where some material emits."""

from __future__ import annotations

import pytest
import torch
from conftest import assert_close

import torchvol as tv
from torchvol.renderer.plan import make_plan


def room(materials, **voxels) -> dict:
    return {
        "image": {"width": 9, "height": 7},
        "camera": {"eye": [0.0, 6.0, -9.0], "target": [0.0, 0.0, 0.0], "fov_y": 40.0},
        "voxels": {"occupancy": {"sdf": {"shape": {"box": {"center": [0.0, 0.0, 0.0], "half_size": [3.0, 3.0, 3.0]}},
                                         "material": 2}},
                   "cells": {"min": [-4, -4, -4], "max": [4, 4, 4]}, "materials": materials, **voxels},
    }


def test_the_colour_form_is_a_table_of_that_colour():
    colour = tv.render(room([[0.2, 0.3, 0.4], [0.8, 0.6, 0.5]]))
    table = tv.render(room([{"color": [0.2, 0.3, 0.4]}, {"color": [0.8, 0.6, 0.5], "emission": [0.0, 0.0, 0.0]}]))
    assert torch.equal(colour.image, table.image) and "voxels.emission" not in colour.stats["plan"]["passes"]
    assert not make_plan(tv.load_scene(room([[0.2, 0.3, 0.4]]))).voxels.emission


def test_emission_is_the_radiance_leaving_a_face():
    """No light, no ambient, no face tones: a hit face shows exactly its material's emission."""
    emit = [0.7, 0.4, 0.1]
    scene = room([[0.5, 0.5, 0.5], {"color": [0.9, 0.9, 0.9], "emission": emit}], ambient=[0.0, 0.0, 0.0],
                 face_tones=[1.0, 1.0, 1.0])
    out = tv.render(scene, dtype=torch.float64)
    hit = out.depth[0, 0] > 0
    assert hit.any()
    assert_close(out.radiance[0].permute(1, 2, 0)[hit], torch.tensor(emit), what="emitted radiance")
    assert make_plan(tv.load_scene(scene)).voxels.emission


@pytest.mark.parametrize("entry, key", [({"emission": [0, -1, 0]}, "voxels.materials[0].emission"),
                                        ({"color": [1, 0, 0], "shine": 1.0}, "voxels.materials[0]"),
                                        ([1, -1, 0], "voxels.materials[0].color")])
def test_bad_materials_are_refused_naming_the_key(entry, key):
    with pytest.raises(ValueError, match=key.replace("[", r"\[").replace("]", r"\]")):
        tv.load_scene(room([entry]))
