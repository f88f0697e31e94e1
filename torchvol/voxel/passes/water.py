"""The water plane of `voxels.water` over the voxels: a ray that reaches the plane before its
surface hit stops there, its colour the Fresnel mix of a reflected and a refracted secondary ray
(total internal reflection from below); paths under water are attenuated by Beer-Lambert. The
maths is `voxel/water.py`'s."""

from __future__ import annotations

import torch
from torch import Tensor

from ...ops.mathops import take_rows
from ...schema.batch import Stacked, take
from ..water import beer, fresnel, plane_hit, reflect, refract, wave_normal
from .secondary import SecondaryRays

__all__ = ["Water"]


class Water:
    """The batch's water (`voxels`: its `Stacked` voxels) at the scenes' `time` (B,) (the waves),
    its secondary rays traced and shaded by `secondary`."""

    def __init__(self, voxels: Stacked, time: Tensor | None, secondary: SecondaryRays):
        self.p, self.time, self.secondary = voxels, time, secondary

    def __call__(self, o: Tensor, d: Tensor, s: Tensor, t_hit: Tensor, color: Tensor, aovs: dict[str, Tensor],
                 section) -> tuple[Tensor, Tensor, Tensor]:
        """Rays o, d [n, 3] of scenes s [n] whose surface hit is at t_hit [n] (inf: none) and colour
        [n, 3] through the water plane -> (hit [n], t [n], colour [n, 3]); the water's AOVs (and
        the water's hit in the others) written into `aovs`."""
        w = self.p.water
        level, absorb = take(w.level, s), take(w.absorption, s)
        under = o[:, 1] < level  # the camera is in the water: its whole primary path is
        t_water = plane_hit(o, d, level)
        # a camera exactly on the plane looking down enters the water where it stands (the limit from above)
        t_water = torch.where((o[:, 1] == level) & (d[:, 1] < 0), torch.zeros_like(t_water), t_water)
        on = t_water < t_hit
        color = torch.where((under & ~on)[:, None], color * beer(absorb, t_hit), color)
        if "water" in aovs:
            aovs["water"] = on.to(o.dtype)[:, None]
        ids = on.nonzero().squeeze(1)
        if not ids.numel():  # no ray met the water: the pass did not run
            return t_hit < torch.inf, t_hit, color
        with section("voxels.water"):
            return self._on_water(o, d, s, ids, on, t_water, t_hit, under, color, aovs, section)

    def _on_water(self, o, d, s, ids, on, t_water, t_hit, under, color, aovs, section):
        """`__call__` for the rays ids [m] that meet the water (`on` [n]) at t_water [n]."""
        w = self.p.water
        level, absorb = take(w.level, s), take(w.absorption, s)
        at = lambda x: take_rows(x, ids)  # noqa: E731  (index_select: 3× faster than x[ids])
        di, si, ui, tw = at(d), at(s), at(under), at(t_water)
        x = at(o) + tw[:, None] * di
        x[:, 1] = at(level)  # exactly on the plane
        up = wave_normal(x, take(w.waves.amplitude, si), take(w.waves.frequency, si), take(w.waves.speed, si),
                         take(self.time, si))
        flat = torch.zeros_like(up)
        flat[:, 1] = 1.0
        sign = torch.where(ui, -1.0, 1.0).to(x.dtype)[:, None]  # the normal on the ray's side
        n = up * sign
        # a grazing ray can meet the back of a tilted wave normal: it sees the flat plane there
        n = torch.where(((di * n).sum(1) >= 0)[:, None], flat * sign, n)
        cos_i = (-(di * n).sum(1)).clamp(0.0, 1.0)
        ior = take(w.ior, si)
        eta = torch.where(ui, ior, 1.0 / ior)
        f = fresnel(cos_i, eta, w.fresnel)
        refr, tir = refract(di, n, eta)
        off = take(w.offset, si)[:, None] * n
        a = at(absorb)
        # the reflected ray stays on the ray's side (in water from below), the refracted one crosses
        refl_col, refl_len = self.secondary.trace_shade(x + off, reflect(di, n), si, section, max_steps=self.p.max_steps)
        refl_col = torch.where(ui[:, None], refl_col * beer(a, refl_len), refl_col)
        refr_col = torch.zeros_like(refl_col)
        floor = torch.full_like(tw, torch.inf)
        k = (~tir).nonzero().squeeze(1)
        if k.numel():
            ik = lambda x: take_rows(x, k)  # noqa: E731
            col, length = self.secondary.trace_shade(ik(x) - ik(off), ik(refr), ik(si), section, max_steps=self.p.max_steps)
            refr_col.index_copy_(0, k, torch.where(ik(ui)[:, None], col, col * beer(ik(a), length)))
            floor.index_copy_(0, k, torch.where(ik(ui), ik(floor), length))
        mixed = f[:, None] * refl_col + (1.0 - f)[:, None] * refr_col
        color.index_copy_(0, ids, torch.where(ui[:, None], mixed * beer(a, tw), mixed))
        if "water_floor_distance" in aovs:
            seen = floor < torch.inf
            aovs["water_floor_distance"].index_copy_(0, ids, torch.where(
                seen, torch.linalg.vector_norm(x + floor[:, None] * refr - at(o), dim=1), torch.zeros_like(tw))[:, None])
        for key in ("normal", "uv", "material", "ao", "shadow"):  # the water's hit, not the voxel's behind it
            if key in aovs:
                if key == "normal":
                    aovs[key].index_copy_(0, ids, up * sign)
                else:
                    aovs[key].index_fill_(0, ids, 0.0)
        t_hit = torch.where(on, t_water, t_hit)
        return t_hit < torch.inf, t_hit, color
