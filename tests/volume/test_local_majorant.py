"""Local majorants of grid media (torchvol/volume/local_majorant.py) and the path tracer's
tracking against them (`path.track_lanes`).

Oracles: the trilinear density itself (`fields.grid.sample_grid`, torch's `grid_sample`) along
segments within a bound's reach must never exceed the bound; the tracking's images against the
one-majorant tracking's (the same integral: means within five standard errors)."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import torchvol as tv
from torchvol.fields.grid import macro_bounds, sample_grid
from torchvol.measure.mitsuba import puff_grid, sigma_for, torchvol_scene
from torchvol.volume import path
from torchvol.volume.local_majorant import bound_at, macro_lanes, macro_majorant

F64 = torch.float64


def _lanes(m):
    """`macro_lanes` of scene 0 for eager lanes (torch columns)."""
    from types import SimpleNamespace

    scene = torch.zeros(1, dtype=torch.long)
    return macro_lanes(m, SimpleNamespace(per_lane=lambda v: list(v[scene].unbind(1)) if v.ndim == 2 else v[scene],
                                          scene=scene, floats=lambda t: t, ints=lambda t: t))


def _spiky_grid(shape, seed: int, fill: float) -> torch.Tensor:
    """Spikes of 1 to 5 in a fraction `fill` of the cells over 0 or a faint floor (0.1)."""
    g = torch.Generator().manual_seed(seed)
    values = 1.0 + torch.rand(shape, generator=g, dtype=F64) * 4.0
    floor = 0.1 if seed % 2 else 0.0
    return torch.where(torch.rand(shape, generator=g, dtype=F64) < fill, values, torch.full_like(values, floor))


@settings(max_examples=60, deadline=None)
@given(shape=st.tuples(*[st.integers(2, 11)] * 3), cells=st.integers(1, 6), fill=st.sampled_from([0.01, 0.05, 0.3, 1.0]),
       seed=st.integers(0, 10_000), box=st.tuples(*[st.floats(0.2, 5.0)] * 3))
def test_a_bound_holds_along_every_segment_within_its_reach(shape, cells, fill, seed, box):
    """From random points in and around the box, along random directions, the trilinear density
    at every point of a segment as long as the bound's reach stays at or below the bound; the
    largest density is the bound of the macro block about it (tight where it peaks)."""
    grid = _spiky_grid(shape, seed, fill)
    low, high = torch.zeros(1, 3, dtype=F64), torch.tensor([box], dtype=F64)
    m = macro_majorant([macro_bounds(grid, low[0], high[0], cells=cells)])
    q = _lanes(m)
    g = torch.Generator().manual_seed(seed + 1)
    n = 2000
    start = (torch.rand(n, 3, generator=g, dtype=F64) * 1.2 - 0.1) * high
    direction = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=F64), dim=1)
    bound, reach = bound_at(q, list(start.unbind(1)), list(direction.unbind(1)))
    along = torch.linspace(0.0, 1.0, 65, dtype=F64)
    points = start[:, None] + direction[:, None] * (reach[:, None, None].clamp(max=10.0) * along[None, :, None])
    density = sample_grid(grid, low[0], high[0], points.reshape(-1, 3)).reshape(n, -1)
    excess = density - bound[:, None]
    worst = int(excess.amax(dim=1).argmax())
    assert float(excess.max()) <= 0.0, (f"the density passes its bound by {float(excess.max()):.3g} on the segment from "
                                        f"{start[worst].tolist()} (bound {float(bound[worst]):.4g}, reach {float(reach[worst]):.4g})")
    if grid.max() > 0:
        peak = torch.stack(torch.unravel_index(grid.argmax(), grid.shape)[::-1]).to(F64)  # its cell centre, (x, y, z)
        centre = (peak + 0.5) / torch.tensor(shape[::-1], dtype=F64) * high[0]
        top, _ = bound_at(q, list(centre[None].unbind(1)), [torch.ones(1, dtype=F64)] * 3)
        assert float(top) == pytest.approx(float(grid.max()), rel=1e-5)


def test_empty_space_is_crossed_in_long_leaps():
    """A grid with density in one corner only: far from it, the bound is 0 and holds for several
    macro cells (the Chebyshev distance to the occupied cell, less one); next to it one cell;
    along a diagonal each cell's side is crossed at 1/√3 the pace, so √3 times as far."""
    grid = torch.zeros(16, 16, 16, dtype=F64)
    grid[0, 0, 0] = 1.0
    m = macro_majorant([macro_bounds(grid, torch.zeros(3, dtype=F64), torch.ones(3, dtype=F64), cells=8)])
    points = [torch.tensor([0.99, 0.01], dtype=F64)] * 3
    along_x = [torch.ones(2, dtype=F64), torch.zeros(2, dtype=F64), torch.zeros(2, dtype=F64)]
    bound, reach = bound_at(_lanes(m), points, along_x)
    cell = 1.0 / 8
    assert float(bound[0]) == 0.0 and float(reach[0]) == pytest.approx(6 * cell * 0.99)
    assert float(bound[1]) == pytest.approx(1.0, rel=1e-5) and float(reach[1]) == pytest.approx(cell * 0.99)
    # along the diagonal a segment moves less along each axis: √3 times as far
    _, diagonal = bound_at(_lanes(m), points, [torch.full((2,), 3**-0.5, dtype=F64)] * 3)
    assert diagonal.tolist() == pytest.approx((reach * 3**0.5).tolist())


def _parity(local: bool, monkeypatch, seeds: int = 4):
    monkeypatch.setattr(path, "LOCAL_MAJORANTS", local)
    grid = puff_grid(16)
    scene = torchvol_scene(grid, sigma_for(grid, 10.0), size=8, spp=1)
    scene["path"] = {"bounces": 64, "samples": 512}
    out = tv.render([scene] * seeds, seed=list(range(seeds)))
    traced = out.radiance.double()
    error = float(traced.var(dim=0).mean().sqrt()) / math.sqrt(traced.numel())
    return float(traced.mean()), error, out.stats


def test_tracking_against_local_majorants_renders_what_one_majorant_does(one_thread, monkeypatch):
    """The parity cloud (optical depth 10, every order): its image by delta and ratio tracking
    against the macro cells' bounds and against one bound, means within five standard errors;
    no collision above a bound; fewer density evaluations."""
    local, local_error, stats = _parity(True, monkeypatch)
    one, one_error, one_stats = _parity(False, monkeypatch)
    error = math.hypot(local_error, one_error)
    assert abs(local - one) <= 5.0 * error, f"local majorants {local:.6g}, one {one:.6g} (standard error {error:.2g})"
    assert error < 0.02 * one  # sharp enough to fail
    assert stats["path"]["above_majorant"] == 0
    assert stats["path"]["local_majorants"] == ["volume0"] and one_stats["path"]["local_majorants"] == []
    assert stats["density_evals"] < 0.75 * one_stats["density_evals"], (stats["density_evals"], one_stats["density_evals"])


@settings(max_examples=40, deadline=None)
@given(octaves=st.integers(1, 5), frequency=st.floats(0.3, 4.0), bias=st.floats(-1.0, 0.3),
       amplitude=st.sampled_from([2.5, 1.0, -1.5]), radial=st.sampled_from([0.0, 0.8]),
       hash=st.sampled_from(["table", "arithmetic"]), cells=st.integers(1, 12), seed=st.integers(0, 10_000))
def test_an_fbm_bound_holds_along_every_segment_within_its_reach(octaves, frequency, bias, amplitude, radial, hash, cells,
                                                                 seed):
    """Value-noise fbm (both hashes, either sign of amplitude, thinned radially or not): the field
    along random segments within their reach from points in and around its box stays at or below
    the bound (`fields.fbm.fbm_macro`), which is not the declared one everywhere (it can fail),
    wherever the segment is inside the box: the medium's bounds, where tracking asks for a bound
    (`path._majorant_at` takes a volume's only inside its span; outside it the field's own noise
    may pass the nearest cell's bound: a start 0.15 off the box's face, seed 0, passed it by 0.004)."""
    from torchvol.fields.fbm import FbmDensity, FbmField, fbm_macro
    from torchvol.schema.batch import stack

    model = FbmDensity(octaves=octaves, frequency=frequency, bias=bias, amplitude=amplitude, radial=radial, hash=hash,
                       seed=seed, offset=(0.3, -1.7, 2.2), center=(0.5, 0.2, 0.4))
    field = FbmField(stack([model], dtype=F64), torch.zeros(1, dtype=F64))
    low, high = torch.tensor([-0.4, 0.0, -0.2], dtype=F64), torch.tensor([1.6, 0.7, 1.1], dtype=F64)
    m = macro_majorant([fbm_macro(field, 0, low, high, cells)])
    q = _lanes(m)
    g = torch.Generator().manual_seed(seed)
    n = 1500
    start = low + (torch.rand(n, 3, generator=g, dtype=F64) * 1.2 - 0.1) * (high - low)
    direction = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=F64), dim=1)
    bound, reach = bound_at(q, list(start.unbind(1)), list(direction.unbind(1)))
    along = torch.linspace(0.0, 1.0, 33, dtype=F64)
    points = start[:, None] + direction[:, None] * (reach[:, None, None].clamp(max=10.0) * along[None, :, None])
    density = field(points.reshape(-1, 3), torch.zeros(points.shape[0] * points.shape[1], dtype=torch.long)).reshape(n, -1)
    inside = ((points >= low) & (points <= high)).all(dim=-1)
    excess = torch.where(inside, density - bound[:, None], -math.inf)
    assert int(inside.sum()) > n, "too few points of the segments inside the box"
    worst = int(excess.amax(dim=1).argmax())
    assert float(excess.max()) <= 0.0, (f"the density passes its bound by {float(excess.max()):.3g} on the segment from "
                                        f"{start[worst].tolist()} (bound {float(bound[worst]):.4g}, reach {float(reach[worst]):.4g})")
    declared = bias + abs(amplitude)
    assert float(m.bound.max()) <= declared + 1e-5 * abs(amplitude)


@settings(max_examples=30, deadline=None)
@given(value=st.floats(0.01, 50.0), base=st.floats(-2.0, 2.0), scale_height=st.floats(0.05, 5.0), cells=st.integers(1, 16),
       seed=st.integers(0, 10_000))
def test_an_exponential_bound_holds_along_every_segment_within_its_reach(value, base, scale_height, cells, seed):
    """An exponential profile in slabs (`fields.exponential.exponential_macro`): along random
    segments within their reach, from points in and around a wide, flat box, the density stays at
    or below the bound, which falls with height (it can fail)."""
    from torchvol.fields.exponential import (
        Exponential,
        ExponentialDensity,
        exponential_macro,
    )
    from torchvol.schema.batch import stack

    model = ExponentialDensity(value=value, base=base, scale_height=scale_height)
    field = Exponential(stack([model], dtype=F64), torch.zeros(1, dtype=F64))
    low, high = torch.tensor([-20.0, -1.0, -15.0], dtype=F64), torch.tensor([20.0, 3.0, 25.0], dtype=F64)
    m = macro_majorant([exponential_macro(field, 0, low, high, cells)])
    g = torch.Generator().manual_seed(seed)
    n = 1500
    start = low + (torch.rand(n, 3, generator=g, dtype=F64) * 1.2 - 0.1) * (high - low)
    direction = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=F64), dim=1)
    bound, reach = bound_at(_lanes(m), list(start.unbind(1)), list(direction.unbind(1)))
    along = torch.linspace(0.0, 1.0, 33, dtype=F64)
    points = start[:, None] + direction[:, None] * (reach[:, None, None] * along[None, :, None])
    inside = ((points >= low) & (points <= high)).all(dim=-1)  # the profile is bounded only over the box
    density = field(points.reshape(-1, 3), torch.zeros(points.shape[0] * points.shape[1], dtype=torch.long)).reshape(n, -1)
    excess = torch.where(inside, density / bound[:, None] - 1.0, -1.0)
    assert float(excess.max()) <= 1e-12, f"the density passes its bound by {float(excess.max()):.3g} of it"
    if m.bound.numel() > 2:  # (a slab's bound is its 3-slab block's: its own or the one below it)
        assert float(m.bound[-1]) < float(m.bound[0])
