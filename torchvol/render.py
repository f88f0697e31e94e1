"""render(): runs a scene's plan over memory-bounded ray chunks and returns a RenderOutput."""

from __future__ import annotations

import math
import time
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Callable, Iterator, Sequence

import torch
from torch import Tensor

from . import noise, post, sky
from .camera import Camera, Rays, strata_shape
from .fields import Field, Grid, make_field, per_scene
from .plan import MarchSettings, at_level, make_plan, march_settings, uses_closed_form, uses_skipping
from .rays import clip_to_ray, intersect_box, intersect_slab, intersect_sphere
from .scene import Scene, load_scene
from .validate import fail
from .volume import light as lighting
from .volume.integrate import frostbite_step
from .volume.sun_volume import SunGrid, sun_transmittance_grid
from .volume.march import COMPACT_BELOW, LN2, expected_depth_fraction, march, march_adaptive
from .volume.skip import MacroGrid, macro_grid, occupied_span
from .voxel.surface import VoxelSurface, surface_aovs

DEFAULT_CHUNK_RAYS = 1 << 16
SLAB_REACH = 1e5  # world units a ray may travel in a slab unless march.max_distance says otherwise


@dataclass
class RenderOutput:
    """`image`, `radiance` (B, 3, H, W); `depth`, `alpha` (B, 1, H, W); `aovs` {name: (B, C, H, W)};
    `camera` the Camera used; `stats` {"passes", "density_evals", "time_s", ...}."""

    image: Tensor
    radiance: Tensor
    depth: Tensor
    alpha: Tensor
    aovs: dict[str, Tensor]
    camera: Camera
    stats: dict


class Timer:
    """Exclusive wall time per pass: a nested section pauses the one around it."""

    def __init__(self):
        self.seconds: dict[str, float] = {}
        self._stack: list[list] = []

    @contextmanager
    def section(self, name: str) -> Iterator[None]:
        now = time.perf_counter()
        if self._stack:
            outer = self._stack[-1]
            self.seconds[outer[0]] = self.seconds.get(outer[0], 0.0) + now - outer[1]
        self._stack.append([name, now])
        try:
            yield
        finally:
            end = time.perf_counter()
            self.seconds[name] = self.seconds.get(name, 0.0) + end - self._stack.pop()[1]
            if self._stack:
                self._stack[-1][1] = end


class Counter:
    def __init__(self):
        self.density_evals = 0


class CountedField:
    """A field that counts the points it evaluates (stats["density_evals"])."""

    def __init__(self, inner: Field, counter: Counter):
        self.inner, self.counter = inner, counter
        self.homogeneous, self.feature_size = inner.homogeneous, inner.feature_size

    def __call__(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        self.counter.density_evals += points.shape[0]
        return self.inner(points, scene_index, lod)

    def signed(self, points: Tensor, scene_index: Tensor, lod: Tensor | None = None) -> Tensor:
        self.counter.density_evals += points.shape[0]
        return self.inner.signed(points, scene_index, lod)


def _t(values, dtype, device) -> Tensor:
    return torch.tensor(values, dtype=dtype, device=device)


def take(param: Tensor, s: Tensor) -> Tensor:
    """Per-scene `param` (B, ...) at scene indices `s` [n] -> [n, ...]. With one scene, a broadcast
    view: the gather would copy n rows of the same value (millions of samples per chunk)."""
    if param.shape[0] == 1:
        return param[0].expand(s.shape[0], *param.shape[1:])
    return param[s]


def gathered(gather: Callable[[Tensor], tuple]) -> Callable[[Tensor], tuple]:
    """`gather(ids)` memoised on the identity of `ids` [n]: the march hands the medium the same ids
    tensor until it compacts, so per-ray gathers (origin, direction, ...) are redone only then."""
    last: list = [None, None]

    def at(ids: Tensor) -> tuple:
        if last[0] is not ids:
            last[0], last[1] = ids, gather(ids)
        return last[1]

    return at


def check_same_structure(scenes: Sequence[Scene]) -> None:
    """Scenes of one batch share everything but numeric values: a SceneError naming the first that
    does not (the dataset uses it to group samples into batches)."""
    first = scenes[0]

    def shape(s: Scene):
        return (
            s.image, s.march, s.post.tonemap, s.post.vignette > 0, s.post.fog is None, None if s.sky is None else s.sky.kind,
            s.sky is not None and (s.sky.halo is None, s.sky.flare is None), s.camera.fov_y is None, s.camera.focal is None,
            [(li.kind, li.shadow) for li in s.lights],
            [(v.bounds.kind, v.density.kind, v.phase.kind, v.shading, v.shader.light, v.shader.ambient_top is None) for v in s.volumes],
            s.camera.matrix is None, _voxel_structure(s.voxels),
        )

    ref = shape(first)
    for b, s in enumerate(scenes[1:], start=1):
        if shape(s) != ref:
            fail(f"scenes[{b}]", "<scene>", "scenes rendered in one batch must share image, march, post, sky kind, "
                 "light and volume kinds; only numeric values may differ")


def _voxel_structure(v):
    if v is None:
        return None
    return (v.occupancy.kind, v.traversal, v.max_steps, len(v.materials) > 1, v.ao is None, v.texture is None,
            v.shadow and v.shadow.steps, v.glow is None, v.rounded, v.fog and v.fog.shadow_steps)


def camera_for(scenes: Sequence[Scene], dtype, device) -> Camera:
    cams = [s.camera for s in scenes]
    if cams[0].matrix is not None:  # given matrices (e.g. the voxel seed's mirrored camera)
        return Camera(K=_t([c.matrix.K for c in cams], dtype, device),
                      world_to_camera=_t([c.matrix.world_to_camera for c in cams], dtype, device),
                      width=scenes[0].image.width, height=scenes[0].image.height)
    focal = None if cams[0].focal is None else _t([c.focal for c in cams], dtype, device)
    fov = None if focal is not None else _t([c.resolved_fov_y for c in cams], dtype, device)
    return Camera.look_at(
        _t([c.eye for c in cams], dtype, device), _t([c.target for c in cams], dtype, device),
        _t([c.up for c in cams], dtype, device), width=scenes[0].image.width, height=scenes[0].image.height,
        fov_y=fov, focal=focal, roll=_t([c.roll for c in cams], dtype, device),
    )


class Lights:
    """Per-scene light parameters: `direction` (L, B, 3) unit, towards the sun; `radiance` (L, B, 3)."""

    def __init__(self, scenes: Sequence[Scene], dtype, device):
        n = len(scenes[0].lights)
        d = _t([[li.direction for li in s.lights] for s in scenes], dtype, device).reshape(len(scenes), n, 3)
        self.direction = torch.nn.functional.normalize(d, dim=-1).transpose(0, 1)
        self.radiance = _t([[[c * li.intensity for c in li.color] for li in s.lights] for s in scenes], dtype, device)
        self.radiance = self.radiance.reshape(len(scenes), n, 3).transpose(0, 1)
        self.shadow = [li.shadow for li in scenes[0].lights]

    def __len__(self) -> int:
        return len(self.shadow)


class VolumeSlot:
    """One volume index across the B scenes: its field and per-scene parameter tensors."""

    def __init__(self, scenes: Sequence[Scene], v: int, counter: Counter, compiled: bool, dtype, device):
        vols = [s.volumes[v] for s in scenes]
        self.spec = vols[0]
        times = _t([s.time for s in scenes], dtype, device)
        inner = make_field([x.density for x in vols], [x.bounds for x in vols], times, compiled=compiled)
        self.field = CountedField(inner, counter)
        self.grid = inner if isinstance(inner, Grid) else None  # a known occupancy: empty space is skipped
        self.sigma_t = _t([x.sigma_t for x in vols], dtype, device)
        self.albedo = _t([x.albedo for x in vols], dtype, device)
        self.emission = _t([x.emission for x in vols], dtype, device)
        self.emissive = any(max(x.emission) > 0 for x in vols)
        kind = self.spec.bounds.kind
        self.bounds_kind = kind
        if kind == "box":
            self.b0 = _t([x.bounds.box.min for x in vols], dtype, device)
            self.b1 = _t([x.bounds.box.max for x in vols], dtype, device)
        elif kind == "sphere":
            self.b0 = _t([x.bounds.sphere.center for x in vols], dtype, device)
            self.b1 = _t([x.bounds.sphere.radius for x in vols], dtype, device)
        else:
            self.b0 = _t([x.bounds.slab.y_min for x in vols], dtype, device)
            self.b1 = _t([x.bounds.slab.y_max for x in vols], dtype, device)
        phase = self.spec.phase.kind
        self.phase_kind = phase
        if phase in ("hg", "mie"):
            self.phase_params = _t([[getattr(x.phase.value, "g")] for x in vols], dtype, device)
        elif phase == "dual_hg":
            self.phase_params = _t([[x.phase.dual_hg.g_forward, x.phase.dual_hg.g_backward, x.phase.dual_hg.weight] for x in vols], dtype, device)
        look = [x.shader for x in vols]
        self.height_gradient = look[0].ambient_top is not None
        if self.height_gradient:
            self.ambient_top = _t([x.ambient_top for x in look], dtype, device)
            self.y_range = _t([self.height_range(x.bounds) for x in vols], dtype, device)  # (B, 2)
        self.look = {
            k: _t([getattr(s, k) for s in look], dtype, device)
            for k in ("light_offset", "light_scale", "ambient", "color_lit", "color_dark", "alpha_scale", "fog")
        }

    @staticmethod
    def height_range(bounds) -> tuple[float, float]:
        if bounds.kind == "box":
            return bounds.box.min[1], bounds.box.max[1]
        if bounds.kind == "sphere":
            return bounds.sphere.center[1] - bounds.sphere.radius, bounds.sphere.center[1] + bounds.sphere.radius
        return bounds.slab.y_min, bounds.slab.y_max

    def ambient(self, p: Tensor, s: Tensor) -> Tensor:
        """The shader look's ambient light at points `p` [n, 3] of scenes `s` [n] -> [n, 3]."""
        if not self.height_gradient:
            return take(self.look["ambient"], s)
        lo, hi = self.y_range[s, 0], self.y_range[s, 1]
        height = ((p[:, 1] - lo) / (hi - lo)).clamp(0.0, 1.0)
        return torch.lerp(take(self.look["ambient"], s), take(self.ambient_top, s), height[:, None])

    def aabb(self, b: int) -> tuple[Tensor, Tensor]:
        """Scene b's bounds as a box (min [3], max [3]); boxes and spheres only."""
        if self.bounds_kind == "box":
            return self.b0[b], self.b1[b]
        return self.b0[b] - self.b1[b], self.b0[b] + self.b1[b]

    def distance_cap(self, settings: MarchSettings) -> float:
        """How far a ray or shadow ray may travel in this volume: `march.max_distance` if given;
        else unbounded for boxes and spheres (their exits are finite: far volumes stay visible)
        and SLAB_REACH for slabs, whose exit is at infinity along their planes."""
        if settings.max_distance is not None:
            return settings.max_distance
        return SLAB_REACH if self.bounds_kind == "slab" else math.inf

    def intersect(self, o: Tensor, d: Tensor, s: Tensor) -> tuple[Tensor, Tensor]:
        """Entry/exit distances of rays `o`, `d` [n, 3] of scenes `s` [n]."""
        if self.bounds_kind == "box":
            return intersect_box(o, d, take(self.b0, s), take(self.b1, s))
        if self.bounds_kind == "sphere":
            return intersect_sphere(o, d, take(self.b0, s), take(self.b1, s))
        return intersect_slab(o, d, take(self.b0, s), take(self.b1, s))

    def phase(self, cos: Tensor, s: Tensor) -> Tensor:
        if self.phase_kind == "isotropic":
            return lighting.isotropic(cos)
        if self.phase_kind == "rayleigh":
            return lighting.rayleigh(cos)
        p = take(self.phase_params, s)
        if self.phase_kind == "hg":
            return lighting.henyey_greenstein(cos, p[:, 0])
        if self.phase_kind == "mie":
            return lighting.mie_cornette_shanks(cos, p[:, 0])
        return lighting.dual_henyey_greenstein(cos, p[:, 0], p[:, 1], p[:, 2])


class Renderer:
    """Holds one batch's per-scene tensors and runs its plan chunk by chunk."""

    def __init__(self, scenes: Sequence[Scene], settings: MarchSettings, *, seeds: Sequence[int], device, dtype, compiled: bool):
        self.scenes, self.settings = scenes, settings
        self.seeds = torch.tensor([int(x) % 2**32 for x in seeds], dtype=torch.int64, device=device)  # (B,)
        self.kw = dict(dtype=dtype, device=device)
        self.timer, self.counter = Timer(), Counter()
        self.plan = make_plan(scenes[0], settings)
        self.names = {(p.kind, p.index): p.name for p in self.plan}
        self.lights = Lights(scenes, dtype, device)
        self.volumes = [VolumeSlot(scenes, v, self.counter, compiled, dtype, device) for v in range(len(scenes[0].volumes))]
        first = scenes[0]
        self.sky_spec = first.sky
        if first.sky is not None:
            skies = [s.sky for s in scenes]
            self.sky = {k: _t([getattr(x, k) for x in skies], dtype, device) for k in ("radiance", "horizon", "slope")}
            if first.sky.kind == "atmosphere":
                atm = [x.atmosphere for x in skies]
                self.atmosphere = {k: _t([getattr(a, k) for a in atm], dtype, device) for k in (
                    "planet_radius", "eye_height", "rayleigh", "mie", "rayleigh_height", "mie_height", "mie_g", "sun_intensity")}
                self.atmosphere["atmosphere_radius"] = _t([a.planet_radius + a.atmosphere_height for a in atm], dtype, device)
            for glow in ("halo", "flare"):
                if getattr(first.sky, glow) is not None:
                    self.sky[glow + "_color"] = _t([getattr(x, glow).color for x in skies], dtype, device)
                    self.sky[glow + "_power"] = _t([getattr(x, glow).power for x in skies], dtype, device)
        self.surface = None
        if first.voxels is not None:
            self.surface = VoxelSurface([s.voxels for s in scenes], self.lights.direction, self.lights.radiance,
                                        dtype=dtype, device=device, compiled=compiled)
        self._sun_grids: dict[tuple[int, int], list[SunGrid]] = {}
        self._macro: dict[tuple[VolumeSlot, int], MacroGrid] = {}  # per render: the skip pass's macro cells
        self.steps_total = 0
        self.truncated = 0
        self.error_estimate = 0.0

    # -- per-chunk passes -------------------------------------------------------------------

    def sky_radiance(self, rays: Rays) -> Tensor:
        s = rays.scene_index
        if self.sky_spec is None:
            return rays.origins.new_zeros(len(rays), 3)
        if self.sky_spec.kind == "constant":
            base = take(self.sky["radiance"], s)
        elif self.sky_spec.kind == "atmosphere":
            atm = self.sky_spec.atmosphere
            base = sky.atmosphere_sky(
                rays.directions, take(self.lights.direction[0], s), steps=atm.steps, light_steps=atm.light_steps,
                **{k: take(v, s) for k, v in self.atmosphere.items()},
            )
        else:
            base = sky.gradient_sky(rays.directions, take(self.sky["horizon"], s), take(self.sky["slope"], s))
        if "halo_color" in self.sky and len(self.lights):
            base = base + sky.sun_glow(rays.directions, take(self.lights.direction[0], s), take(self.sky["halo_color"], s), take(self.sky["halo_power"], s))
        return base

    def dither(self, rays: Rays) -> Tensor | None:
        mode = self.settings.dither
        if mode == "none":
            return None
        if mode == "sin":  # the seeds' fract(sin(px.x*73 + px.y*311) * 43758.5453), GL pixel coordinates
            px = rays.pixel[:, 0]
            py = self.scenes[0].image.height - 1 - rays.pixel[:, 1]
            x = torch.sin((px * 73 + py * 311).to(rays.origins.dtype)) * 43758.5453
            return self.settings.dither_scale * (x - torch.floor(x))
        spp = self.scenes[0].image.spp
        sub = torch.arange(len(rays), device=rays.pixel.device) % spp  # chunks hold whole pixels
        cells = torch.stack([rays.pixel[:, 0] * spp + sub, rays.pixel[:, 1], self.seeds[rays.scene_index]], dim=1)
        return noise.hash3(cells, 0x5EED, dtype=rays.origins.dtype)

    def jitter(self, start: int, stop: int) -> Tensor | None:
        """Sub-pixel offsets [n, 2] of rays start:stop: stratum + a hash of (seed, ray), so the same
        seed gives the same rays whatever the chunking. None (stratum centres) for spp == 1."""
        spp = self.scenes[0].image.spp
        if spp == 1:
            return None
        ids = torch.arange(start, stop, device=self.kw["device"])
        nx, ny = strata_shape(spp)
        per_scene = self.scenes[0].image.width * self.scenes[0].image.height * spp
        sample, scene = ids % spp, ids // per_scene
        cells = torch.stack([ids % per_scene, self.seeds[scene], torch.zeros_like(ids)], dim=1)
        xi = torch.stack([noise.hash3(cells, 0x717E + k, dtype=torch.float64) for k in (0, 1)], dim=1)
        strata = torch.stack([sample % nx, sample // nx], dim=1).to(torch.float64)
        off = (strata + xi) / torch.tensor([nx, ny], dtype=torch.float64, device=ids.device) - 0.5
        return off.clamp(-0.5 + 1e-7, 0.5 - 1e-7).to(self.kw["dtype"])

    def radiance_scale(self, scene_index: Tensor) -> Tensor:
        """What `march.tolerance` is relative to, per ray [R]: the brightest light channel (1 if
        the scene has no light, e.g. pure emission)."""
        if not len(self.lights):
            return torch.ones_like(scene_index, dtype=self.kw["dtype"])
        return self.lights.radiance.amax(dim=(0, 2))[scene_index].clamp_min(1e-12)

    def lod(self, t: Tensor) -> Tensor | None:
        if self.settings.lod_scale is None:
            return None
        octaves = 5
        return octaves - torch.floor(torch.log2(1.0 + t * self.settings.lod_scale)).long()

    def sun_response(self, slot: VolumeSlot, d: Tensor, s: Tensor) -> Tensor:
        """E · p(θ) of each sun seen along directions `d` [n, 3] of scenes `s` [n] -> [L, n, 3]. Suns
        are directional: θ is the same all along a ray, so a march computes this once per ray."""
        return torch.stack([
            take(self.lights.radiance[l], s) * slot.phase((d * take(self.lights.direction[l], s)).sum(dim=1), s)[:, None]
            for l in range(len(self.lights))
        ])

    def in_scatter(self, slot: VolumeSlot, v: int, p: Tensor, s: Tensor, sigma_t: Tensor, response: Tensor) -> Tensor:
        """Σ over suns of σs · p(θ) · E · T_light at points `p` [n, 3] of extinction `sigma_t` [n];
        `response` [L, n, 3]: each sun's E · p(θ) there (`sun_response`). -> [n, 3]."""
        out = p.new_zeros(p.shape[0], 3)
        sigma_s = take(slot.albedo, s) * sigma_t
        for l in range(len(self.lights)):
            sun = take(self.lights.direction[l], s)
            radiance = response[l] * sigma_s[:, None]
            shadow = self.lights.shadow[l]
            if shadow is not None and shadow.method == "grid":
                with self.timer.section(self.names[("shadow", l)]):
                    grids = self.sun_grids(slot, v, l)
                    radiance = radiance * per_scene(p, s, len(grids), lambda b, i, q: grids[b].lookup(q, sigma_t[i]))[:, None]
            elif shadow is not None:
                with self.timer.section(self.names[("shadow", l)]):
                    exit_t = slot.intersect(p, sun, s)[1].clamp(0.0, slot.distance_cap(self.settings))
                    radiance = radiance * lighting.shadow_transmittance(
                        p, sun, exit_t, lambda q, owner: slot.sigma_t[s[owner]] * slot.field(q, s[owner]),
                        steps=shadow.steps, growth=shadow.growth, first_step=shadow.first_step,
                    )[:, None]
            out = out + radiance
        return out

    def sun_grids(self, slot: VolumeSlot, v: int, l: int) -> list[SunGrid]:
        """Transmittance to sun `l` through volume `v`, one grid per scene, built on first use and
        kept for every chunk of this render."""
        key = (v, l)
        if key not in self._sun_grids:
            resolution = self.lights.shadow[l].resolution
            grids = []
            for b in range(len(self.scenes)):
                lo, hi = slot.aabb(b)

                def owner(q: Tensor, b: int = b) -> Tensor:
                    return torch.full((q.shape[0],), b, dtype=torch.long, device=q.device)

                def extinction(q: Tensor, b: int = b) -> Tensor:  # called on nodes inside the bounds only
                    return slot.sigma_t[b] * slot.field(q, owner(q))

                grids.append(sun_transmittance_grid(extinction, lo, hi, self.lights.direction[l][b], resolution=resolution,
                                                    chord=lambda o, d: slot.intersect(o, d, owner(o))))
            self._sun_grids[key] = grids
        return self._sun_grids[key]

    def physical_medium(self, slot: VolumeSlot, v: int, rays: Rays, *, signed: bool = False):
        """The medium of a physically shaded volume: (σ_t [n], in-scattered + emitted source [n, 3]).
        `signed`: σ_t is the field's signed value times its σ_t, negative where there is no density
        (what `march_adaptive` interpolates between samples); the source is that of the density."""
        o, d, s_all = rays.origins, rays.directions, rays.scene_index
        threshold = self.settings.density_threshold
        response = self.sun_response(slot, d, s_all) if len(self.lights) else None  # [L, R, 3]

        at = gathered(lambda ids: (s_all[ids], o[ids], d[ids], None if response is None else response[:, ids]))

        def medium(ids: Tensor, t: Tensor, dt: Tensor):
            s, o_ids, d_ids, response_ids = at(ids)
            p = torch.addcmul(o_ids, t[:, None], d_ids)
            raw = (slot.field.signed if signed else slot.field)(p, s, self.lod(t))
            density = raw.clamp_min(0.0) if signed else raw
            sigma_raw = take(slot.sigma_t, s) * raw
            sigma_t = sigma_raw.clamp_min(0.0) if signed else sigma_raw
            source = p.new_zeros(p.shape[0], 3)
            lit = ((density > threshold) & (dt > 0)).nonzero().squeeze(1)  # dt = 0: a finished ray not dropped yet
            if lit.numel() and response is not None:
                source[lit] = self.in_scatter(slot, v, p[lit], s[lit], sigma_t[lit], response_ids[:, lit])
            if slot.emissive:
                source = source + take(slot.emission, s) * density[:, None]
            return sigma_raw, source

        return medium

    def shader_medium(self, slot: VolumeSlot, v: int, rays: Rays, background: Tensor):
        """The seeds' look: alpha = density·scale; colour = mix(lit, dark, density)·(sun·dif + ambient),
        fogged towards the sky colour by 1 − exp(−fog·t²)."""
        o, d, s_all = rays.origins, rays.directions, rays.scene_index
        look, threshold = slot.look, self.settings.density_threshold
        derivative = slot.spec.shader.light == "derivative" and len(self.lights) > 0

        at = gathered(lambda ids: (s_all[ids], o[ids], d[ids]))

        def medium(ids: Tensor, t: Tensor, dt: Tensor):
            s, o_ids, d_ids = at(ids)
            p = torch.addcmul(o_ids, t[:, None], d_ids)
            lod = self.lod(t)
            density = slot.field(p, s, lod)
            alpha = torch.zeros_like(density)
            color = p.new_zeros(p.shape[0], 3)
            keep = (density > threshold).nonzero().squeeze(1)
            if keep.numel():
                sk, dk, tk = s[keep], density[keep], t[keep]
                lin = slot.ambient(p[keep], sk)
                if derivative:
                    with self.timer.section(self.names[("derivative_light", 0)]):
                        sun = self.lights.direction[0][sk]
                        ahead = slot.field(p[keep] + look["light_offset"][sk, None] * sun, sk, None if lod is None else lod[keep])
                        dif = lighting.derivative_light(dk, ahead, scale=look["light_scale"][sk])
                        lin = self.lights.radiance[0][sk] * dif[:, None] + lin
                col = torch.lerp(look["color_lit"][sk], look["color_dark"][sk], dk[:, None]) * lin
                fog = look["fog"][sk]
                col = torch.lerp(col, background[ids][keep], (1.0 - torch.exp(-fog * tk * tk))[:, None])
                color[keep] = col
                alpha[keep] = dk * look["alpha_scale"][sk]
            return alpha, color

        return medium

    def volume(self, slot: VolumeSlot, v: int, rays: Rays, background: Tensor, t_limit: Tensor | None = None) -> dict[str, Tensor]:
        """Radiance [n,3], transmittance, weight sums, median t and entry t of one volume, marched
        up to `t_limit` [n] (the voxel surface's distance) where given."""
        st = self.settings
        t_near, t_far = slot.intersect(rays.origins, rays.directions, rays.scene_index)
        shader = slot.spec.shading == "shader"
        if shader:  # the seeds: march whenever the exit is ahead, from max(t_near, 0)
            t0 = t_near.clamp_min(0.0)
            t1 = t_far.clamp_max(slot.distance_cap(st))
            hit = (t_far >= 0) & (t_far >= t_near)
        else:
            t0, t1, hit = clip_to_ray(t_near, t_far, slot.distance_cap(st))
        if t_limit is not None:
            t1 = torch.minimum(t1, t_limit)
            hit = hit & (t1 > t0)
        if uses_closed_form(self.scenes[0], v, st):
            with self.timer.section(self.names[("closed_form", v)]):
                return self.closed_form(slot, v, rays, t0, t1, hit)
        with self.timer.section(self.names[("march", v)]):
            if shader:
                medium = self.shader_medium(slot, v, rays, background)
            else:
                medium = self.physical_medium(slot, v, rays, signed=st.tolerance is not None)
            if st.tolerance is not None and not shader:
                res = march_adaptive(
                    t0, t1, hit, medium, tolerance=st.tolerance, integrator=st.integrator,
                    radiance_scale=self.radiance_scale(rays.scene_index), min_transmittance=st.min_transmittance,
                    # a field's detail caps the steps; a smooth one's steps are capped by march.steps
                    max_steps_per_span=st.rule.steps if st.rule.placement == "count" and slot.field.feature_size is None else None,
                    max_step=None if slot.field.feature_size is None else 0.5 * take(slot.field.feature_size, rays.scene_index),
                )
                self.error_estimate = max(self.error_estimate, float(res.error.max()) if len(res.error) else 0.0)
            else:
                occupied, marched = None, hit
                if uses_skipping(self.scenes[0], v, st):
                    with self.timer.section(self.names[("skip", v)]):
                        occupied, marched = self.occupied_span(slot, rays, t0, t1, hit)
                res = march(
                    t0, t1, marched, medium, rule=st.rule, integrator=st.integrator,
                    semantics="shader" if shader else "segments", dither=self.dither(rays),
                    min_transmittance=st.min_transmittance, occupied=occupied,
                    # a grid sample is one trilinear lookup, cheaper than a compaction; fbm octaves are not
                    compact_below=COMPACT_BELOW if slot.grid is not None else 1.0,
                )
        self.steps_total += int(res.steps.sum())
        self.truncated += int(res.truncated.sum())
        radiance, trans = res.radiance, res.transmittance
        if shader:  # the template's clamp(sum, 0, 1)
            radiance, trans = radiance.clamp(0.0, 1.0), 1.0 - (1.0 - trans).clamp(0.0, 1.0)
        return dict(radiance=radiance, transmittance=trans, weight_sum=res.weight_sum, weighted_t=res.weighted_t,
                    median_t=res.median_t, t0=torch.where(hit, t0, torch.full_like(t0, math.inf)))

    def occupied_span(self, slot: VolumeSlot, rays: Rays, t0: Tensor, t1: Tensor, hit: Tensor):
        """((t_first, t_last), hit) [n]: the span of each ray through the grid's occupied macro
        cells; rays that cross none leave `hit`."""
        first, last = t0.clone(), t1.clone()
        found = torch.zeros_like(hit)
        for b in range(len(self.scenes)):
            idx = (hit & (rays.scene_index == b)).nonzero().squeeze(1)
            if idx.numel():
                grid = slot.grid
                if (slot, b) not in self._macro:
                    self._macro[slot, b] = macro_grid(grid.occupancy(b), grid.box_min[b], grid.box_max[b])
                first[idx], last[idx], found[idx] = occupied_span(
                    rays.origins[idx], rays.directions[idx], t0[idx], t1[idx], self._macro[slot, b], grid.box_min[b])
        return (first, last), hit & found

    def closed_form(self, slot: VolumeSlot, v: int, rays: Rays, t0: Tensor, t1: Tensor, hit: Tensor) -> dict[str, Tensor]:
        """Homogeneous medium, unshadowed suns: one exact frostbite segment over the whole chord,
        evaluated on the rays that hit only."""
        n = len(rays)
        out = dict(radiance=t0.new_zeros(n, 3), transmittance=torch.ones_like(t0), weight_sum=torch.zeros_like(t0),
                   weighted_t=torch.zeros_like(t0), median_t=torch.zeros_like(t0), t0=torch.full_like(t0, math.inf))
        ids = hit.nonzero().squeeze(1)
        if ids.numel() == 0:
            return out
        s, d, a, b = rays.scene_index[ids], rays.directions[ids], t0[ids], t1[ids]
        length = b - a
        mid = rays.origins[ids] + (0.5 * (a + b))[:, None] * d
        density = slot.field(mid, s)
        sigma_t = take(slot.sigma_t, s) * density
        source = take(slot.emission, s) * density[:, None]
        if len(self.lights):
            source = source + self.in_scatter(slot, v, mid, s, sigma_t, self.sun_response(slot, d, s))
        radiance, trans = frostbite_step(source, sigma_t, length)
        alpha = 1.0 - trans
        t_mean = a + length * expected_depth_fraction(sigma_t * length)
        median = torch.where(trans <= 0.5, a + LN2 / sigma_t.clamp_min(torch.finfo(a.dtype).tiny), torch.zeros_like(a))
        for key, value in dict(radiance=radiance, transmittance=trans, weight_sum=alpha, weighted_t=alpha * t_mean,
                               median_t=median, t0=a).items():
            out[key][ids] = value
        return out

    def chunk(self, rays: Rays) -> dict[str, Tensor]:
        n = len(rays)
        background = None
        if self.sky_spec is not None:
            with self.timer.section("sky"):
                background = self.sky_radiance(rays)
        surf = None
        if self.surface is not None:
            sky_bg = background if background is not None else rays.origins.new_zeros(n, 3)
            surf = self.surface.run(rays.origins, rays.directions, rays.scene_index, rays.forward_cos, sky_bg, self.timer.section)
        t_limit = None if surf is None else surf["t"]
        parts = [self.volume(slot, v, rays, background, t_limit) for v, slot in enumerate(self.volumes)]
        with self.timer.section("composite"):
            radiance = rays.origins.new_zeros(n, 3)
            trans = torch.ones_like(rays.origins[:, 0])
            wsum, wt, median = torch.zeros_like(trans), torch.zeros_like(trans), torch.zeros_like(trans)
            if parts:
                order = torch.argsort(torch.stack([p["t0"] for p in parts]), dim=0)  # [V, n]: front to back per ray
                ordered = {}
                for key in ("radiance", "transmittance", "weight_sum", "weighted_t", "median_t"):
                    stacked = torch.stack([p[key] for p in parts])  # [V, n] or [V, n, 3]
                    index = order.view(*order.shape, *([1] * (stacked.dim() - 2))).expand_as(stacked)
                    ordered[key] = stacked.gather(0, index)
                for k in range(len(parts)):
                    part_trans = ordered["transmittance"][k]
                    radiance = radiance + trans[:, None] * ordered["radiance"][k]
                    wsum = wsum + trans * ordered["weight_sum"][k]
                    wt = wt + trans * ordered["weighted_t"][k]
                    crossed = (median == 0) & (trans > 0.5) & (trans * part_trans <= 0.5)
                    median = torch.where(crossed, ordered["median_t"][k], median)
                    trans = trans * part_trans
            behind = background if surf is None else surf["color"]  # the shaded surface where hit
            if behind is not None:
                radiance = radiance + trans[:, None] * behind
        if ("flare", None) in self.names:
            with self.timer.section("post.flare"):
                s = rays.scene_index
                radiance = radiance + sky.sun_glow(rays.directions, take(self.lights.direction[0], s), take(self.sky["flare_color"], s), take(self.sky["flare_power"], s))
        alpha = 1.0 - trans
        distance = torch.where(wsum > 0, wt / wsum.clamp_min(torch.finfo(wsum.dtype).tiny), torch.zeros_like(wsum))
        valid = (alpha >= self.settings.depth_threshold) & (wsum > 0)
        distance = torch.where(valid, distance, torch.zeros_like(distance))
        extra = {}
        if surf is not None:  # the surface is an opaque terminal weight T at its distance
            hit, ts = surf["hit"], torch.where(surf["hit"], surf["t"], torch.zeros_like(trans))
            denom = (wsum + trans).clamp_min(torch.finfo(wsum.dtype).tiny)
            distance = torch.where(hit, (wt + trans * ts) / denom, distance)
            median = torch.where(hit & (median == 0), ts, median)
            alpha = torch.where(hit, torch.ones_like(alpha), alpha)
            extra = surf["aovs"]
        return dict(radiance=radiance, alpha=alpha, depth=distance * rays.forward_cos,
                    distance=distance, depth_median=median * rays.forward_cos, **extra)


def render(
    scene,
    *,
    seed: int | Sequence[int] = 0,
    device: str | torch.device = "cpu",
    dtype: torch.dtype | None = None,
    chunk_rays: int = DEFAULT_CHUNK_RAYS,
    compile: bool = False,
    progress: Callable[[int], None] | None = None,
) -> RenderOutput:
    """Render a scene (or a list of scenes of one structure, as one batch).

    `scene`: a Scene, a dict, a .toml path or a preset name (or a list of those). `seed` (one int, or
    one per scene) drives the dither and sub-pixel jitter, hashed per (seed, pixel, sample): a scene
    renders the same alone or anywhere in a batch, for any chunking. `dtype` defaults to the quality level's (float64 for reference).
    `chunk_rays` bounds peak memory. `compile` runs the noise kernels under torch.compile.
    `progress(pixels)`, where given, is called after each chunk with the pixels it finished."""
    seeds = list(seed) if isinstance(seed, (list, tuple)) else None
    if isinstance(chunk_rays, bool) or not isinstance(chunk_rays, int) or chunk_rays < 1:
        fail("chunk_rays", chunk_rays, "expected an integer >= 1")
    if dtype not in (None, torch.float32, torch.float64):
        fail("dtype", dtype, "expected torch.float32, torch.float64 or None (the quality level's)")
    try:
        device = torch.device(device)
        torch.empty(0, device=device)
    except (RuntimeError, TypeError, AssertionError) as err:
        fail("device", str(device), f"not a usable torch device here ({str(err).splitlines()[0]})")
    scenes = [at_level(load_scene(s)) for s in (scene if isinstance(scene, (list, tuple)) else [scene])]
    if not scenes:
        fail("scene", scene, "expected at least one scene")
    check_same_structure(scenes)
    seeds = [seed] * len(scenes) if seeds is None else seeds
    if len(seeds) != len(scenes) or any(isinstance(x, bool) or not isinstance(x, int) for x in seeds):
        fail("seed", seed, f"expected an integer or one integer per scene ({len(scenes)})")
    settings = march_settings(scenes[0].march)
    dtype = dtype or settings.dtype
    start = time.perf_counter()
    r = Renderer(scenes, settings, seeds=seeds, device=torch.device(device), dtype=dtype, compiled=compile)
    img = scenes[0].image
    b, h, w, spp = len(scenes), img.height, img.width, img.spp
    with r.timer.section("rays"):
        camera = camera_for(scenes, dtype, torch.device(device))
    pixels = b * h * w
    chunk_pixels = max(1, chunk_rays // spp)  # chunks hold whole pixels: sub-samples resolve in place
    keys = ["radiance", "alpha", "depth"] + (["distance", "depth_median"] if scenes[0].volumes else [])
    if scenes[0].voxels is not None:
        keys += surface_aovs(scenes[0].voxels, len(scenes[0].lights))
    buffers: dict[str, Tensor] = {}
    for first in range(0, pixels, chunk_pixels):
        last = min(pixels, first + chunk_pixels)
        with r.timer.section("rays"):
            rays = camera.ray_range(first * spp, last * spp, spp=spp, offsets=r.jitter(first * spp, last * spp))
        values = r.chunk(rays)
        with r.timer.section("resolve") if spp > 1 else _noop():
            for key in keys:
                value = values[key].to(torch.float32).reshape(last - first, spp, -1)
                if key == "material":  # ids do not average: the first sub-sample's
                    value = value[:, 0]
                elif key in ("radiance", "alpha", "normal", "uv", "ao", "shadow") or spp == 1:
                    value = value.mean(dim=1)
                else:  # depths: mean over the sub-samples that hit
                    value = value.sum(dim=1) / (value > 0).sum(dim=1).clamp_min(1)
                if key not in buffers:  # channel-major: for one scene the buffer already is (1, C, H, W)
                    buffers[key] = torch.empty(value.shape[1], pixels, dtype=torch.float32, device=value.device)
                buffers[key][:, first:last] = value.T
        if progress is not None:
            progress(last - first)
    images = {k: v.view(-1, b, h, w).transpose(0, 1).contiguous() for k, v in buffers.items()}  # no copy when b = 1
    radiance, alpha, depth = images.pop("radiance"), images.pop("alpha"), images.pop("depth")
    aovs = images
    n_rays = pixels * spp
    image = _post(scenes, r, radiance, aovs.get("distance"))
    stats = {
        "passes": [p.name for p in r.plan],
        "density_evals": r.counter.density_evals,
        "time_s": {p.name: r.timer.seconds.get(p.name, 0.0) for p in r.plan},
        "total_s": time.perf_counter() - start,
        "rays": n_rays,
        "march_steps": r.steps_total,
        "truncated_rays": r.truncated,
        **({"error_estimate": r.error_estimate} if settings.tolerance is not None else {}),
        **({"voxel_steps": r.surface.steps_total} if r.surface is not None else {}),
        "dtype": str(dtype).removeprefix("torch."),
    }
    return RenderOutput(image=image, radiance=radiance, depth=depth, alpha=alpha, aovs=aovs, camera=camera, stats=stats)


@contextmanager
def _noop():
    yield


def _post(scenes: Sequence[Scene], r: Renderer, radiance: Tensor, distance: Tensor | None) -> Tensor:
    p = scenes[0].post
    x = radiance
    names = {pp.kind: pp.name for pp in r.plan}
    if "fog" in names:
        with r.timer.section(names["fog"]):
            color = torch.tensor([s.post.fog.color for s in scenes], dtype=x.dtype)
            density = torch.tensor([s.post.fog.density for s in scenes], dtype=x.dtype)
            x = post.distance_fog(x, distance, color, density)
    if "exposure" in names:
        with r.timer.section(names["exposure"]):
            x = x * torch.tensor([s.post.exposure for s in scenes], dtype=x.dtype)[:, None, None, None]
    if "tonemap" in names:
        with r.timer.section(names["tonemap"]):
            if p.tonemap == "smoothstep":
                x = post.smoothstep(p.smoothstep_edges[0], p.smoothstep_edges[1], x)
            elif p.tonemap == "reinhard":
                x = post.reinhard(x.clamp_min(0.0))
            else:
                x = post.aces(x.clamp_min(0.0))
    if "vignette" in names:
        with r.timer.section(names["vignette"]):
            x = post.vignette(x, p.vignette)
    return x.clamp(0.0, 1.0)
