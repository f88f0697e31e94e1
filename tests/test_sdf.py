"""SDF primitives and CSG against closed forms."""

import math

import torch
from conftest import assert_close

from torchvol.geometry import sdf


def test_sphere_and_box_distances():
    p = torch.tensor([[3.0, 0.0, 0.0], [0.0, 0.0, 0.0], [2.0, 2.0, 0.0], [0.5, 0.2, -0.1], [3.0, 4.0, 1.0]], dtype=torch.float64)
    assert_close(sdf.sd_sphere(p, 1.0), [2.0, -1.0, math.sqrt(8) - 1, math.sqrt(0.3) - 1, math.sqrt(26) - 1], what="sphere")
    # box half size 1: outside face, inside, outside edge, inside near a face, outside corner
    assert_close(sdf.sd_box(p, [1.0, 1.0, 1.0]), [2.0, -1.0, math.sqrt(2), -0.5, math.sqrt(4 + 9)], what="box")


def test_rounded_box_is_box_shrunk_then_inflated():
    p = torch.randn(200, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    out = sdf.sd_rounded_box(p, 0.5, 0.2)
    q = (p.abs() - 0.3).clamp_min(0.0)
    assert_close(out, q.norm(dim=1) - 0.2, what="rounded box")
    assert_close(sdf.sd_rounded_box(p, 0.5, 0.0), torch.where(sdf.sd_box(p, 0.5) > 0, sdf.sd_box(p, 0.5), torch.zeros(200, dtype=torch.float64)),
                 what="radius 0 outside")


def test_csg_and_tree():
    p = torch.tensor([[0.0, 0.0, 0.0], [5.9, 5.9, 5.9], [6.5, 0.0, 0.0]], dtype=torch.float64)
    tree = {"subtraction": {"a": {"box": {"center": (0, 0, 0), "half_size": (6, 6, 6)}},
                            "b": {"sphere": {"center": (0, 0, 0), "radius": 7.5}}}}
    expected = torch.maximum(sdf.sd_box(p, 6.0), -sdf.sd_sphere(p, 7.5))
    assert_close(sdf.evaluate(tree, p), expected, what="carved box")
    assert (sdf.evaluate(tree, p)[:2] > 0).tolist() == [True, False]  # centre carved, corner kept
    a, b = torch.tensor([1.0, -2.0]), torch.tensor([0.5, 3.0])
    assert sdf.union(a, b).tolist() == [0.5, -2.0]
    assert sdf.intersection(a, b).tolist() == [1.0, 3.0]
    assert sdf.subtraction(a, b).tolist() == [1.0, -2.0]
    u = {"union": [{"sphere": {"center": (2, 0, 0), "radius": 1}}, {"sphere": {"center": (-2, 0, 0), "radius": 1}}]}
    assert_close(sdf.evaluate(u, torch.tensor([[0.0, 0.0, 0.0]], dtype=torch.float64)), [1.0], what="union")
