"""`voxels.gi = { method = "path", bounces, samples }`: the furnace test (a closed room of albedo a
emitting e, no lights, sky, ambient or face tones, shows e · (1 + a + … + a^B) everywhere, whatever
the room's shape), the error falling as 1/√S, determinism, and nothing changed without it."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import assert_close

import torchvol as tv
from torchvol.ops import lanes
from torchvol.renderer.plan import make_plan
from torchvol.voxel.gi import bounce_direction_lanes, bounce_uniform_lanes

INNER = {"box": {"box": {"center": [0.0, 0.0, 0.0], "half_size": [3.0, 2.0, 3.0]}},
         "sphere": {"sphere": {"center": [0.0, 0.0, 0.0], "radius": 3.2}},
         # an L-shaped room: two boxes
         "L": {"union": [{"box": {"center": [-1.0, 0.0, 0.0], "half_size": [2.0, 2.0, 3.0]}},
                         {"box": {"center": [1.0, 0.0, -2.0], "half_size": [2.0, 2.0, 1.0]}}]}}


def room(materials, *, shape="box", gi=None, size=(8, 8), **voxels) -> dict:
    """A closed room (a shell around `shape`), the camera inside, no lights, ambient or face tones."""
    outer = {"box": {"center": [0.0, 0.0, 0.0], "half_size": [5.0, 4.0, 5.0]}}
    return {
        "image": {"width": size[0], "height": size[1]},
        "camera": {"eye": [0.3, 0.2, -0.6], "target": [0.0, -0.3, 2.0], "fov_y": 80.0},
        "voxels": {"occupancy": {"sdf": {"shape": {"subtraction": {"a": outer, "b": INNER[shape]}}, "material": 1}},
                   "cells": {"min": [-6, -6, -6], "max": [6, 6, 6]}, "materials": materials,
                   "ambient": [0.0, 0.0, 0.0], "face_tones": [1.0, 1.0, 1.0],
                   **({} if gi is None else {"gi": gi}), **voxels},
    }


@pytest.mark.parametrize("shape", ["box", "sphere", "L"])
@pytest.mark.parametrize("a, e, bounces", [(0.5, 0.2, 3), (0.8, 0.1, 2), (0.3, [0.9, 0.5, 0.2], 1), (0.95, 0.05, 6)])
def test_furnace(shape, a, e, bounces):
    e = torch.tensor([e] * 3 if isinstance(e, float) else e, dtype=torch.float64)
    scene = room([{"color": [a] * 3, "emission": e.tolist()}], shape=shape, gi={"bounces": bounces, "samples": 4})
    out = tv.render(scene, dtype=torch.float64)
    assert bool((out.depth > 0).all()), "the camera must see walls only"
    expected = e * sum(a ** k for k in range(bounces + 1))
    got = out.radiance[0].permute(1, 2, 0).reshape(-1, 3)
    assert torch.allclose(got.double(), expected.expand_as(got), rtol=0.01, atol=0.0)
    assert out.stats["passes"] == ["rays", "voxels.dda", "voxels.shade", "voxels.gi", "composite"]


def test_error_falls_as_one_over_root_samples():
    """An emissive ceiling over grey walls: RMS error against a 1024-sample reference at S = 4, 16, 64."""
    def scene(samples):
        s = room([[0.6] * 3, {"color": [0.6] * 3, "emission": [2.0] * 3}], gi={"bounces": 2, "samples": samples}, size=(6, 6))
        s["voxels"]["occupancy"] = {"function": {"fn": ceiling}}
        return s
    ref = tv.render(scene(1024), dtype=torch.float64).radiance
    errs = [(tv.render(scene(S), dtype=torch.float64).radiance - ref).pow(2).mean().sqrt().item() for S in (4, 16, 64)]
    slope = (math.log(errs[2]) - math.log(errs[0])) / (math.log(64) - math.log(4))
    assert -0.7 < slope < -0.3, (errs, slope)


def test_passes_accumulate_progressively():
    """`image.passes` draws new paths each pass (their seeds change): 8 passes of 4 paths land as close
    to the reference as one pass of 32 would (well under one pass of 4)."""
    def scene(samples, passes=1):
        s = room([[0.6] * 3, {"color": [0.6] * 3, "emission": [2.0] * 3}], gi={"bounces": 2, "samples": samples}, size=(6, 6))
        s["voxels"]["occupancy"] = {"function": {"fn": ceiling}}
        s["image"]["passes"] = passes
        return s
    ref = tv.render(scene(1024), dtype=torch.float64).radiance
    rms = lambda out: (out.radiance - ref).pow(2).mean().sqrt().item()
    one, eight = rms(tv.render(scene(4), dtype=torch.float64)), rms(tv.render(scene(4, passes=8), dtype=torch.float64))
    assert eight < 0.5 * one, (one, eight)


def ceiling(c: torch.Tensor) -> torch.Tensor:
    """Cells [N, 3] of a closed 6×4×6 room (walls material 1) whose ceiling (y = 2) is material 2."""
    x, y, z = c.unbind(1)
    wall = (x < -3) | (x >= 3) | (y < -2) | (y >= 2) | (z < -3) | (z >= 3)
    return torch.where(wall, torch.where(y >= 2, 2, 1), 0)


def test_determinism_alone_and_in_a_batch():
    def scene(seed):
        s = room([[0.6] * 3, {"color": [0.6] * 3, "emission": [2.0] * 3}], gi={"bounces": 2, "samples": 3}, size=(5, 4))
        s["voxels"]["occupancy"] = {"function": {"fn": ceiling}}
        return s
    a, b = tv.render(scene(0), seed=3), tv.render(scene(0), seed=3)
    assert torch.equal(a.image, b.image)
    both = tv.render([scene(0), scene(0)], seed=[3, 4])
    assert torch.equal(both.image[0], a.image[0]) and not torch.equal(both.image[1], a.image[0])


def test_no_gi_is_unplanned_and_bitwise_unchanged():
    scene = room([{"color": [0.5] * 3, "emission": [0.2] * 3}], ambient=[0.3, 0.3, 0.3])
    out = tv.render(scene)
    assert "voxels.gi" not in out.stats["passes"] and not make_plan(tv.load_scene(scene)).voxels.gi


def test_a_point_light_inside_a_closed_room_odd_size():
    """The hard case: all light comes from a point light inside the room, shadowed, over 2 bounces;
    GI only adds light (albedo ≥ 0), and the image is finite at an odd size."""
    base = room([[0.7, 0.6, 0.5]], size=(7, 5), shadow={"steps": 32})
    base["lights"] = [{"kind": "point", "position": [0.5, 1.0, 1.0], "intensity": 5.0}]
    direct = tv.render(base, dtype=torch.float64).radiance
    base["voxels"]["gi"] = {"bounces": 2, "samples": 8}
    out = tv.render(base, dtype=torch.float64)
    assert torch.isfinite(out.radiance).all() and out.radiance.shape[-2:] == (5, 7)
    assert bool((out.radiance >= direct - 1e-12).all()) and bool((out.radiance > direct).any())


def test_bounce_directions_are_cosine_distributed():
    # the paths' uniforms (hashed from their cells) and directions (the path tracer's Lambert bounce)
    n = torch.nn.functional.normalize(torch.tensor([[0.3, -0.8, 0.2]], dtype=torch.float64), dim=1).expand(20000, 3)
    cells = [torch.arange(20000, dtype=torch.int32), torch.full((20000,), 7, dtype=torch.int32), torch.zeros(20000, dtype=torch.int32)]
    u1, u2 = bounce_uniform_lanes(cells, 1, n[:, 0])
    assert float(u1.min()) >= 0.0 and float(u1.max()) < 1.0 and abs(float(u2.mean()) - 0.5) < 0.01
    d = torch.stack(bounce_direction_lanes(lanes.columns(n), u1, u2), dim=1)
    assert_close(d.norm(dim=1), torch.ones(20000, dtype=torch.float64), what="unit length")
    cos = (d * n).sum(1)
    assert bool((cos >= 0).all())
    assert abs(cos.mean().item() - 2.0 / 3.0) < 0.01  # E[cos θ] under pdf cos θ / π


def test_bad_gi_is_refused():
    with pytest.raises(ValueError, match="voxels.gi.bounces"):
        tv.load_scene(room([[0.5] * 3], gi={"bounces": 0}))
    with pytest.raises(ValueError, match="voxels.gi.method"):
        tv.load_scene(room([[0.5] * 3], gi={"method": "photon"}))


def test_furnace_per_scene_in_a_batch():
    """Albedo, emission and room shape differ per scene of one batch; each scene gets its own value."""
    cases = [(0.5, 0.2, "box"), (0.8, 0.1, "L")]
    scenes = [room([{"color": [a] * 3, "emission": [e] * 3}], shape=shape, gi={"bounces": 2, "samples": 2})
              for a, e, shape in cases]
    out = tv.render(scenes, dtype=torch.float64)
    for b, (a, e, _) in enumerate(cases):
        expected = torch.full_like(out.radiance[b], e * (1 + a + a * a))
        assert torch.allclose(out.radiance[b].double(), expected.double(), rtol=0.01, atol=0.0)


def _open_room(**extra) -> dict:
    """A room open at the front (paths leave it for the sky), lit by a shadowed point light and a
    sun, a glossy and an emissive material, seen from outside."""
    def cells(c):
        shell = (c.abs().amax(dim=1) == 4) & (c[:, 2] > -4)
        return torch.where(shell, 1 + (c[:, 1] > 0).long(), torch.where((c[:, 0] == 1) & (c[:, 1] < -2), 3, 0))

    return {"image": {"width": 20, "height": 16}, "camera": {"eye": [0.5, 0.3, -9.0], "target": [0.0, -0.5, 0.0], "fov_y": 60.0},
            "sky": {"kind": "gradient", "horizon": [0.6, 0.7, 0.8], "slope": [0.2, 0.1, 0.0]},
            "lights": [{"kind": "point", "position": [0.5, 2.5, -1.0], "intensity": 8.0},
                       {"kind": "sun", "direction": [0.3, 1.0, -0.6], "intensity": 2.0}],
            "voxels": {"occupancy": {"function": {"fn": cells}}, "cells": {"min": [-4, -4, -4], "max": [5, 5, 5]},
                       "materials": [[0.7, 0.6, 0.5], {"color": [0.8, 0.8, 0.8], "roughness": 0.3, "metallic": 0.5},
                                     {"color": [0.3, 0.5, 0.3], "emission": [0.5, 0.2, 0.1]}],
                       "shadow": {"steps": 24}, "gi": {"bounces": 2, "samples": 3}, **extra}}


GI_KERNEL = {
    "sky, glossy and emissive faces, two lights": _open_room(),
    "distance LOD": _open_room(gi={"bounces": 2, "samples": 4, "lod": {"near": 6.0, "far": 12.0, "samples": 1}}),
    "shadow rays through a medium": {**_open_room(), "volumes": [
        {"bounds": {"box": {"min": [-3.0, 0.5, -3.0], "max": [3.0, 1.5, 3.0]}}, "sigma_t": 1.5, "albedo": 0.0,
         "density": {"fbm": {"octaves": 2, "frequency": 1.0, "seed": 3}}}]},
}


@pytest.mark.parametrize("name", list(GI_KERNEL))
def test_the_paths_in_the_kernel_are_the_eager_paths(name):
    """`passes.paths.path_lanes` as one Dr.Jit kernel over a chunk's paths against the same lanes
    on torch columns (the reference): the image within float rounding (the directions' sin, cos
    and sqrt), the same DDA steps and density evaluations; the paths matter (without GI the image
    is far off)."""
    from torchvol.runtime.compilation import drjit_available

    if not drjit_available():
        pytest.skip("Dr.Jit's LLVM backend is not available")
    scene = GI_KERNEL[name]
    kernel, eager = tv.render(scene, seed=2), tv.render(scene, seed=2, compile="off")
    peak = float(eager.radiance.abs().max())
    assert_close(kernel.radiance / peak, eager.radiance / peak, atol=1e-5, what=f"{name}: radiance / peak")
    assert kernel.stats["voxel_steps"] == eager.stats["voxel_steps"]
    assert kernel.stats["density_evals"] == eager.stats["density_evals"]
    flat = tv.render({**scene, "voxels": {k: v for k, v in scene["voxels"].items() if k != "gi"}}, seed=2)
    assert float((flat.radiance - kernel.radiance).abs().max()) > 1e-2 * peak


@pytest.mark.parametrize("compile", ["kernels", "off"])
@pytest.mark.parametrize("where", ["a floor under the sky", "a closed room under a sky"])
def test_paths_that_all_leave_or_none_leave_the_grid(where, compile):
    """Every path leaves at its first bounce (the second walks no cell: no path is alive), or none
    ever does (no sky is looked up): finite, and the floor's paths see the sky."""
    if where == "a floor under the sky":
        scene = {"image": {"width": 12, "height": 10}, "camera": {"eye": [0.2, 3.0, -4.0], "target": [0.0, 0.0, 0.0]},
                 "sky": {"kind": "constant", "radiance": [0.5, 0.6, 0.7]},
                 "voxels": {"occupancy": {"function": {"fn": lambda c: (c[:, 1] == 0).long()}},
                            "cells": {"min": [-3, 0, -3], "max": [4, 1, 4]}, "materials": [[0.6, 0.6, 0.6]],
                            "ambient": [0.0, 0.0, 0.0], "gi": {"bounces": 2, "samples": 2}}}
    else:
        scene = {**room([{"color": [0.5] * 3, "emission": [1.0] * 3}], gi={"bounces": 2, "samples": 2}),
                 "sky": {"kind": "gradient"}}  # (a kernel of its own: it once met an empty batch of paths)
    out = tv.render(scene, compile=compile)
    assert bool(torch.isfinite(out.radiance).all()) and float(out.radiance.min()) >= 0.0
    hit = out.depth[0, 0] > 0
    assert bool((out.radiance[0, 0][hit] > 0).all())  # the sky's (or the panel's) light through the paths
