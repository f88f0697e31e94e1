"""DDA traversal against the slow reference (sorted plane crossings walked one at a time): every
hit agrees — cell, face axis, distance, step count — on random grids and rays, axis-parallel rays and
constructed exact ties; hybrid traversal finds the same hits with fewer steps."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchvol.ops.grid_ops import chebyshev_distance
from torchvol.voxel.dda import hybrid_traverse, reference_traverse, traverse


@pytest.fixture(autouse=True)
def one_thread():  # small tensors: threads only add overhead (and contention on shared cores)
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _grid(seed: int, shape=(6, 7, 8), p=0.1):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(shape, generator=g) < p


def _lookup(occ, lo):
    def f(c, ids):
        i = c - lo
        return occ[i[:, 2], i[:, 1], i[:, 0]].long()
    return f


def _compare(o, d, occ, lo, hi, max_steps):
    h = traverse(o, d, _lookup(occ, lo), lo, hi, max_steps=max_steps)
    bad = []
    for r in range(o.shape[0]):
        ref = reference_traverse(o[r], d[r], lambda c: bool(occ[c[2] - lo[2], c[1] - lo[1], c[0] - lo[0]]), lo, hi, max_steps=max_steps)
        got = (bool(h.hit[r]), int(h.steps[r]))
        exp = (ref[0], ref[4])
        if ref[0]:
            got += (tuple(h.cell[r].tolist()), int(h.axis[r]), float(h.t[r]))
            exp += (ref[1], ref[2], ref[3])
        if got != exp:
            bad.append((r, got, exp, o[r].tolist(), d[r].tolist()))
    assert not bad, f"{len(bad)} of {o.shape[0]} rays disagree with the reference; first: {bad[0]}"
    return h


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), p=st.floats(0.02, 0.3), lo=st.tuples(*[st.integers(-5, 5)] * 3),
       inside=st.booleans(), max_steps=st.integers(1, 40))
def test_random_rays_match_reference(seed, p, lo, inside, max_steps):
    g = torch.Generator().manual_seed(seed)
    occ = _grid(seed, p=p)
    lo = torch.tensor(lo)
    hi = lo + torch.tensor([8, 7, 6])
    n = 48
    span = (hi - lo).double()
    o = lo + (torch.rand(n, 3, generator=g, dtype=torch.float64) * (1.0 if inside else 3.0) - (0.0 if inside else 1.0)) * span
    d = lo + torch.rand(n, 3, generator=g, dtype=torch.float64) * span - o
    d[:8, 1:] = 0  # axis-parallel
    d[8:16, ::2] = 0
    d[16:24, 2] = 0
    d = d / d.norm(dim=1, keepdim=True).clamp_min(1e-12)
    d[d.norm(dim=1) == 0] = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    _compare(o, d, occ, lo, hi, max_steps)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1),
       dirs=st.lists(st.tuples(*[st.sampled_from([-2, -1, 0, 1, 2])] * 3).filter(any), min_size=16, max_size=16),
       fracs=st.lists(st.tuples(*[st.sampled_from([0.0, 0.25, 0.5])] * 3), min_size=16, max_size=16))
def test_exact_ties_step_one_axis_first_of_xyz(seed, dirs, fracs):
    """Directions with components in ratios 0 : 1 : 2 from quarter-cell origins cross edges and
    corners exactly: the DDA steps one axis at a time (x, y, z order), like the reference."""
    occ = _grid(seed, p=0.15)
    lo = torch.tensor([-3, -3, -3])
    hi = lo + torch.tensor([8, 7, 6])
    g = torch.Generator().manual_seed(seed)
    cells = torch.randint(-6, 7, (16, 3), generator=g).double()
    o = cells + torch.tensor(fracs, dtype=torch.float64)
    d = torch.tensor(dirs, dtype=torch.float64)
    d = d / d.norm(dim=1, keepdim=True)
    _compare(o, d, occ, lo, hi, 40)


def test_tie_visits_the_x_neighbour_first():
    """A diagonal through a cell edge visits (1, 0) then (1, 1): one axis per step, x first."""
    occ = torch.zeros(1, 3, 3, dtype=torch.bool)
    occ[0, 0, 1] = True  # cell (1, 0, 0): the x neighbour of the start, touched only at an edge
    o = torch.tensor([[0.5, 0.5, 0.5]], dtype=torch.float64)
    d = torch.tensor([[1.0, 1.0, 0.0]], dtype=torch.float64) / math.sqrt(2)
    h = traverse(o, d, _lookup(occ, torch.tensor([0, 0, 0])), [0, 0, 0], [3, 3, 1], max_steps=10)
    assert bool(h.hit[0]) and h.cell[0].tolist() == [1, 0, 0] and int(h.axis[0]) == 0 and int(h.steps[0]) == 2


def test_camera_inside_and_step_limit():
    occ = torch.zeros(4, 4, 4, dtype=torch.bool)
    occ[2, 2, 3] = True
    o = torch.tensor([[0.5, 2.5, 2.5], [0.5, 2.5, 2.5]], dtype=torch.float64)
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    look = _lookup(occ, torch.tensor([0, 0, 0]))
    h = traverse(o, d, look, [0, 0, 0], [4, 4, 4], max_steps=4)
    assert h.hit.tolist() == [True, True] and h.t[0].item() == 2.5 and h.steps[0].item() == 4
    h = traverse(o, d, look, [0, 0, 0], [4, 4, 4], max_steps=3)
    assert h.hit.tolist() == [False, False] and h.steps[0].item() == 3


def test_hybrid_same_hits_fewer_steps():
    g = torch.Generator().manual_seed(3)
    occ = torch.zeros(24, 24, 24, dtype=torch.bool)
    occ[:6] = torch.rand(6, 24, 24, generator=g) < 0.6  # a rough floor, open space above
    lo, hi = torch.tensor([0, 0, 0]), torch.tensor([24, 24, 24])
    n = 400
    o = torch.rand(n, 3, generator=g, dtype=torch.float64) * 24
    o[:, 2] = 23.5
    d = torch.rand(n, 3, generator=g, dtype=torch.float64) * 24 - o
    d[:40, 0] = 0
    d = d / d.norm(dim=1, keepdim=True)
    look = _lookup(occ, lo)
    dist = chebyshev_distance(occ)
    plain = traverse(o, d, look, lo, hi, max_steps=200)
    hyb = hybrid_traverse(o, d, look, lambda c, ids: dist[c[:, 2], c[:, 1], c[:, 0]].long(), lo, hi, max_steps=200)
    assert torch.equal(plain.hit, hyb.hit)
    h = plain.hit
    assert torch.equal(plain.cell[h], hyb.cell[h]) and torch.equal(plain.axis[h], hyb.axis[h])
    err = (plain.t[h] - hyb.t[h]).abs().max().item()
    assert err == 0.0, f"hit distances differ by up to {err}"
    assert hyb.steps.sum() < 0.8 * plain.steps.sum(), (int(hyb.steps.sum()), int(plain.steps.sum()))


def test_chebyshev_distance_is_exact():
    occ = torch.zeros(9, 9, 9, dtype=torch.bool)
    occ[4, 4, 4] = True
    dist = chebyshev_distance(occ, max_radius=16)
    k, j, i = torch.meshgrid(*[torch.arange(9)] * 3, indexing="ij")
    expected = torch.maximum(torch.maximum((k - 4).abs(), (j - 4).abs()), (i - 4).abs())
    assert torch.equal(dist.long(), expected)
