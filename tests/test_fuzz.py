"""The fuzz (torchvol.measure.fuzz): random scenes over every volumetric technique give no NaN, no
Inf, no exception but a ValueError naming the key, and every output in range. `tools/fuzz.py`
runs 1,000 (docs/VOLUMES.md, "Fuzz"); here a slice of them, and the checker against scenes that
break each promise."""

from __future__ import annotations

import types

import pytest
import torch

from torchvol.measure.fuzz import REFUSED, check, fuzz


def _show(failures) -> str:
    return "\n".join(f"scene {f.index}: {f.error.strip().splitlines()[-1]}" for f in failures)


def test_thirty_random_scenes_keep_every_promise(one_thread):
    failures, refused = fuzz(30, seed=0)
    assert not failures, _show(failures)
    assert refused < 20  # most scenes render: the fuzz exercises the renderer, not the validator


@pytest.mark.slow
def test_two_hundred_more(one_thread):
    failures, _ = fuzz(200, seed=1, first=30)
    assert not failures, _show(failures)


def _output(**bad):
    good = dict(image=torch.zeros(1, 3, 2, 2), radiance=torch.zeros(1, 3, 2, 2), depth=torch.zeros(1, 1, 2, 2),
                alpha=torch.zeros(1, 1, 2, 2), aovs={})
    return types.SimpleNamespace(**{**good, **bad})


@pytest.mark.parametrize("render, verdict", [
    (lambda scene, **kw: _output(), None),
    (lambda scene, **kw: _output(radiance=torch.full((1, 3, 2, 2), float("nan"))), "radiance: non-finite"),
    (lambda scene, **kw: _output(image=torch.full((1, 3, 2, 2), 1.5)), "out of [0, 1]"),
    (lambda scene, **kw: _output(depth=torch.full((1, 1, 2, 2), -1.0)), "negative"),
])
def test_the_checker_sees_each_broken_promise(render, verdict):
    out = check({"lights": []}, render)
    assert out is None if verdict is None else verdict in out


def test_the_checker_tells_a_refusal_from_a_crash():
    def refuse(scene, **kw):
        raise ValueError("volumes[0].sigma_t: got -1.0; expected >= 0")

    def vague(scene, **kw):
        raise ValueError("something is wrong")

    def crash(scene, **kw):
        raise TypeError("'NoneType' object is not subscriptable")

    assert check({}, refuse) == REFUSED
    assert "naming no key" in check({}, vague)
    assert "TypeError" in check({}, crash)
