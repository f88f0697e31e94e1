"""render(): executes a batch's plan over memory-bounded ray chunks and returns a RenderOutput.

The plan (`torchvol.renderer.plan`) has made every decision; this module holds a render's state
(`RenderContext`: the batch's per-scene tensors, its lights and volumes, counters and timer) and
runs each planned pass by looking it up: skies in `SKIES`, volume strategies in `STRATEGIES`, post
effects in `POST`. `stats["passes"]` and `stats["time_s"]` record what ran.
"""

from __future__ import annotations

import time
from contextlib import nullcontext
from dataclasses import dataclass, field, replace
from functools import partial, reduce
from typing import Callable, Sequence

import torch
from torch import Tensor

from ..fields import DENSITIES
from ..fields.edge import EdgeField
from ..geometry.bounds import BOUNDS, intersect_kernel
from ..geometry.camera import Camera, Rays
from ..geometry.sampling import march_dither, ray_keys, subpixel_jitter
from ..light.atmosphere import (
    AirPath,
    air_path,
    gather_air,
    ground_radiance,
    planet_frame,
    rows_of,
    sun_transmittance,
)
from ..light.lights import LIGHTS, LightSource, sun_index
from ..light.phase import PHASES
from ..light.sky import SKIES, sky_kernel, sun_glow
from ..ops.mathops import take_rows
from ..post import POST, View
from ..runtime.compilation import CompileMode, compile_mode
from ..runtime.threads import glue_on_one_thread
from ..schema.batch import Stacked, stack, take
from ..schema.validate import fail, integer, is_integer
from ..terrain import TerrainSurface, path_surface
from ..volume import kernel_march, path, path_kernel
from ..volume.ambient import sky_mean
from ..volume.composite import Media, composite_volumes, finish
from ..volume.joint import march_joint
from ..volume.shading import SHADINGS
from ..volume.strategy import STRATEGIES
from ..voxel.path_surface import path_surface as voxel_path_surface
from ..voxel.surface import VoxelSurface
from .accumulate import Accumulator, pass_seeds
from .aovs import AOVS, RESOLVE
from .labels import per_ray as label_rays
from .plan import Plan, VolumePass, make_plan
from .prepare import prepare
from .stats import CountedField, Counts, Timer
from .surfaces import VoxelOccluder, surface_pass, terrain_id, voxel_shadow_steps

DEFAULT_CHUNK_RAYS = 1 << 16


@dataclass
class RenderOutput:
    """`image`, `radiance` (B, 3, H, W); `depth`, `alpha` (B, 1, H, W); `aovs` {name: (B, C, H, W)};
    `camera` the Camera used; `stats` {"passes", "density_evals", "time_s", "plan", ...};
    `context` the render's `RenderContext` where `render(..., keep_context=True)`, else None."""

    image: Tensor
    radiance: Tensor
    depth: Tensor
    alpha: Tensor
    aovs: dict[str, Tensor]
    camera: Camera
    stats: dict
    context: RenderContext | None = field(default=None, repr=False)  # with render(..., keep_context=True)


@dataclass
class VolumeState:
    """One volume index across the batch: its parameters, plan, kinds, field and per-render caches
    (sun grids per light, skip macro grids per scene)."""

    params: Stacked
    plan: VolumePass
    field: CountedField
    bounds: object  # Kind
    phase: object  # Kind
    shading: object  # Kind
    sun_grids: dict = field(default_factory=dict)
    macro: dict = field(default_factory=dict)
    ambient_bottom: Tensor | None = None  # (B, 3) the ambient radiance (at the bottom of the bounds)

    def intersect(self, o: Tensor, d: Tensor, s: Tensor, *, kernel: bool = False) -> tuple[Tensor, Tensor]:
        """Entry/exit distances [n] of rays `o`, `d` [n, 3] of scenes `s` [n]; `kernel` (the volume
        marches in a Dr.Jit kernel): as one too where the bounds' kind says it pays (`traced_interval`)."""
        if kernel and self.bounds.traced_interval:
            return intersect_kernel(self.bounds, self.params.bounds.value, o, d, s)
        return self.bounds.fn(self.params.bounds.value, o, d, s)


class RenderContext:
    """A render's state: the batch (`Stacked` scenes at their quality level), its plan, seeds,
    lights, volumes and surfaces (`surface` the pass that runs: the voxel surface, the terrain or
    both; `terrain` and `voxels` the occluders shadow rays meet), and what the render records
    (timer, counts)."""

    def __init__(self, batch: Stacked, plan: Plan, *, seeds: Sequence[int], device):
        # `batch` stacked in the plan's dtype; the plan decided the dtype and what runs as a kernel
        self.batch, self.plan, self.settings = batch, plan, plan.settings
        self.seeds = torch.tensor([int(x) % 2**32 for x in seeds], dtype=torch.int64, device=device)  # (B,)
        self.dtype, self.device = plan.dtype, device
        self.timer, self.counts = Timer(), Counts()
        self.path_media = None  # the paths' media (`volume.path.Media`), made on the first chunk
        self.times = batch.time
        self.lights = [LightSource(LIGHTS[li.kind], li) for li in batch.lights]
        if plan.atmosphere:  # the sun reaches every point of the scene through the air
            self.lights[plan.sun].through = sun_through_air(batch.atmosphere, self.lights[plan.sun])
        self.volumes = [self._volume(vp) for vp in plan.volumes]
        self.voxel_surface = self.voxels = self.terrain = None
        if plan.voxels is not None:
            self.voxel_surface = VoxelSurface(
                batch.voxels, self.lights, plan.voxels, {a: AOVS[a].channels for a in plan.aovs}, dtype=plan.dtype,
                device=device, drjit=plan.walk == "drjit", time=self.times,
                sky=None if plan.sky is None else lambda d, s: sky_toward(self, d, s), transmittance=self.shadow_rays,
                occluder_lanes=lambda uses, s: kernel_march.surface_lanes_of(self, uses, s))
            self.voxels = VoxelOccluder(self.voxel_surface.tracer, voxel_shadow_steps(batch.voxels))
        if plan.terrain is not None:
            self.terrain = TerrainSurface(batch.terrain, self.lights, plan.terrain, plan.aovs, self.shadow_rays, plan.kernels,
                                          lambda uses, s: kernel_march.surface_lanes_of(self, uses, s))
        # the one the scene has, or both as one: each ray the nearer hit (renderer/surfaces.py)
        self.surface = surface_pass(self.voxel_surface, self.terrain, terrain_id(batch))

    def _volume(self, vp: VolumePass) -> VolumeState:
        params = self.batch.volumes[vp.index]
        bounds, density = BOUNDS[params.bounds.kind], DENSITIES[params.density.kind]
        extra = {}
        if density.caps.get("needs_box"):
            extra = dict(zip(("box_min", "box_max"), bounds.aabb(params.bounds.value)))
        inner = density.fn(params.density.value, self.times, **extra)
        if params.edge is not None:
            inner = EdgeField(inner, bounds.caps["depth"], params.bounds.value, params.edge)
        state = VolumeState(params, vp, CountedField(inner, self.counts), bounds, PHASES[params.phase.kind],
                            SHADINGS[vp.shading])
        if vp.ambient:
            amb = params.ambient
            state.ambient_bottom = amb.radiance if amb.radiance is not None else sky_mean(
                SKIES[self.batch.sky.kind].fn, self.batch.sky, self.sun(), len(params), dtype=self.dtype, device=self.device)
        return state

    def shadow_rays(self, use, p: Tensor, s: Tensor, direction: Tensor, distance: Tensor,
                    times: Tensor | None = None) -> Tensor:
        """What a surface's or a label's shadow ray (LightPass `use`) sees besides that surface (the
        volumes, the other surfaces), as the plan says: `kernel_march.surface_shadows`, one Dr.Jit
        kernel where the render runs them."""
        return kernel_march.surface_shadows(self, use, p, s, direction, distance, times)

    def dither(self, rays: Rays) -> Tensor | None:
        """The march's start offset per ray [R] (`march.dither`: hashed from the seed and pixel, the
        seeds' sin hash, or None: none)."""
        st, image = self.settings, self.batch.image
        return march_dither(rays, st.dither, scale=st.dither_scale, seeds=self.seeds, height=image.height, spp=image.spp,
                            kernel=self.plan.kernels)

    def radiance_scale(self, scene_index: Tensor) -> Tensor:
        """What `march.tolerance` is relative to, per ray [R]: the brightest light channel (a point
        light's at unit distance; 1 if the scene has no light, e.g. pure emission)."""
        if not self.lights:
            return torch.ones_like(scene_index, dtype=self.dtype)
        return torch.stack([li.radiant for li in self.lights]).amax(dim=(0, 2))[scene_index].clamp_min(1e-12)

    def sun(self) -> Tensor | None:
        """(B, 3) towards the scene's sun (`Plan.sun`; skies, halo and flare need one), None: no sun."""
        return None if self.plan.sun is None else self.lights[self.plan.sun].direction


def sun_through_air(atm: Stacked, sun: LightSource) -> Callable[[Tensor, Tensor], Tensor]:
    """The `[atmosphere]`'s transmittance towards `sun` from world points: `fn(points [n, 3], s [n])
    -> [n, 3]` (`LightSource.through`)."""
    def through(points: Tensor, s: Tensor) -> Tensor:
        air = gather_air(atm, s)
        return sun_transmittance(planet_frame(points, air), take(sun.direction, s), air, atm.light_steps)

    return through


def sky_radiance(ctx: RenderContext, rays: Rays) -> Tensor:
    """The sky behind each ray [n, 3], with the sun's halo where the sky has one."""
    return sky_toward(ctx, rays.directions, rays.scene_index)


def sky_toward(ctx: RenderContext, directions: Tensor, s: Tensor) -> Tensor:
    """The sky [n, 3] seen along unit directions [n, 3] of scenes s [n] (with the halo)."""
    sky = ctx.batch.sky
    kind = SKIES[ctx.plan.sky]
    if ctx.plan.sky_backend == "drjit" and "lanes" in kind.caps:  # the sky and its halo one kernel
        return sky_kernel(kind, sky, directions, s, ctx.sun() if ctx.plan.halo else None)
    if ctx.plan.sky_backend == "drjit":
        base = kind.fn(sky, directions, s, ctx.sun(), kernel=True)
    else:
        base = kind.fn(sky, directions, s, ctx.sun())
    if ctx.plan.halo:
        base = base + sun_glow(directions, take(ctx.sun(), s), take(sky.halo.color, s), take(sky.halo.power, s))
    return base


def run_chunk(ctx: RenderContext, rays: Rays) -> dict[str, Tensor]:
    """Every per-ray pass of the plan on one chunk of rays -> per-ray outputs and AOVs."""
    plan, n = ctx.plan, len(rays)
    background = None
    if plan.sky is not None:
        with ctx.timer.section("sky"):
            background = sky_radiance(ctx, rays)
    surf = None
    if ctx.surface is not None:
        sky_bg = background if background is not None else rays.origins.new_zeros(n, 3)
        args = (rays.origins, rays.directions, rays.scene_index, sky_bg, ctx.timer.section)
        if plan.voxels is not None and plan.voxels.gi:  # its paths are hashed from (seed, pixel, sample)
            surf = ctx.surface.run(*args, keys=ray_keys(rays, seeds=ctx.seeds, spp=ctx.batch.image.spp))
        else:
            surf = ctx.surface.run(*args)
    air = None
    if plan.atmosphere:
        with ctx.timer.section("atmosphere"):
            air = air_along(ctx, rays)
    t_limit = None if surf is None else surf.t
    if air is not None:  # the planet's ground stops what no surface stopped before it
        t_limit = air.ground if surf is None else torch.where(surf.hit, surf.t, air.ground)
    media = march_media(ctx, rays, background, t_limit, air)
    with ctx.timer.section("composite"):
        behind = background if surf is None else surf.color  # the shaded surface where hit
        ground = None
        if air is not None:
            behind, ground = behind_the_air(ctx, air, rays.scene_index, behind, surf)
        volumes = composite_volumes(media.parts, rays.origins[:, 0])
        out = finish(volumes, behind, surf, rays.forward_cos, ctx.settings.depth_threshold)
        if ground is not None:
            out = on_the_ground(out, ground, rays)
    if plan.path is not None:
        with ctx.timer.section("path"):
            traced = path_radiance(ctx, rays, background)
            out["radiance"] = out["radiance"] + traced if plan.path[3] == "march" else traced
    if plan.labels is not None:
        out.update(label_rays(ctx, rays, media, volumes, surf))
    if plan.flare:
        with ctx.timer.section("post.flare"):
            s, flare = rays.scene_index, ctx.batch.sky.flare
            out["radiance"] = out["radiance"] + sun_glow(rays.directions, take(ctx.sun(), s), take(flare.color, s),
                                                         take(flare.power, s))
    return out


def march_media(ctx: RenderContext, rays: Rays, background: Tensor | None, t_limit: Tensor | None,
                air: AirPath | None = None) -> Media:
    """The chunk's volumes as the plan marches them: the joint march of the physically shaded ones
    and the air (`Plan.joint`, `air` along the rays or None), then each other volume by its
    strategy (`STRATEGIES`), seen through the air in front of its entry; `background` [n, 3] (the
    sky) or None, `t_limit` [n] (a surface hit, the ground) or None."""
    joint, parts, members, shares = ctx.plan.joint, [], [], None
    if joint is not None:
        with ctx.timer.section(joint.name):
            together = march_joint(ctx, [ctx.volumes[v] for v in joint.volumes], rays, background, t_limit,
                                   shares=joint.shares, air=air)
        parts, members, shares = [together.part], [joint.volumes], together.shares
    for v, vol in enumerate(ctx.volumes):
        if not vol.plan.joint:
            part = STRATEGIES[vol.plan.strategy](ctx, vol, rays, background, t_limit)
            if air is not None:  # (its own look's march, outside the joint one: the air in front of it)
                entry = torch.where(torch.isfinite(part.t0), part.t0, torch.zeros_like(part.t0))
                part = replace(part, radiance=part.radiance * air.transmittance(torch.arange(len(rays), device=entry.device), entry))
            parts.append(part)
            members.append((v,))
    return Media(parts, members, shares)


def path_radiance(ctx: RenderContext, rays: Rays, background: Tensor | None) -> Tensor:
    """The chunk's radiance [n, 3] path-traced through the physical media (`[path]`, `volume.path`):
    the sky `background` [n, 3] (None: black) where a camera ray leaves them, the sky where a
    scattered path does; with `single = "march"` only what the march leaves out (`Media.marched_first`)."""
    bounces, samples, backend, single = ctx.plan.path
    if ctx.path_media is None:
        terrain, voxels = ctx.batch.terrain, ctx.batch.voxels
        makers = ([] if terrain is None else [partial(path_surface, terrain)]) + (
            [] if voxels is None else [partial(voxel_path_surface, voxels, ctx.voxel_surface.grid)])
        ctx.path_media = path.media(ctx.volumes, ctx.dtype, path_surfaces(makers), air=ctx.batch.atmosphere,
                                    marched_first=single == "march")
    sky = None if ctx.plan.sky is None else lambda d, s: sky_toward(ctx, d, s)
    return path.radiance(ctx.path_media, ctx.lights, rays, background, sky, bounces=bounces, samples=samples,
                         keys=ray_keys(rays, seeds=ctx.seeds, spp=ctx.batch.image.spp),
                         trace=path_kernel.trace_kernel if backend == "drjit" else None)


def path_surfaces(makers: list) -> Callable | None:
    """The scene's opaque surfaces (each `Media.surface`'s maker: the terrain's, the voxels') as
    the paths' one (`path.surfaces`: each ray the nearer, as the march's `surface_pass`), None: none."""
    if not makers:
        return None
    return lambda *args, **kw: reduce(path.surfaces, [make(*args, **kw) for make in makers])


def air_along(ctx: RenderContext, rays: Rays) -> AirPath:
    """The `[atmosphere]`'s air along a chunk's rays, lit by the scene's sun (`AirPath`)."""
    atm, s, sun = ctx.batch.atmosphere, rays.scene_index, ctx.lights[ctx.plan.sun]
    kernel = ctx.plan.joint.backend == "drjit"
    return air_path(rays.origins, rays.directions, take(sun.direction, s), take(sun.radiant, s),
                    gather_air(atm, s, kernel=kernel), steps=atm.steps, light_steps=atm.light_steps, kernel=kernel)


def behind_the_air(ctx: RenderContext, air: AirPath, s: Tensor, behind: Tensor | None, surf) -> tuple[Tensor, Tensor]:
    """What lies behind the media of rays of scenes `s` [n], seen through all the air in front of
    it: the surface where one was hit (`surf`), else the planet's ground where the ray meets it
    (lit by the sun through the air), else `behind` [n, 3] (the sky, None: space, black). -> (its
    radiance [n, 3], the distance to the ground [n], 0 where the ray does not end on it)."""
    n = air.enter.shape[0]
    rows = torch.arange(n, device=air.enter.device)
    on_surface = torch.zeros(n, dtype=torch.bool, device=rows.device) if surf is None else surf.hit
    ground = torch.isfinite(air.ground) & ~on_surface
    behind = air.enter.new_zeros(n, 3) if behind is None else behind
    ids = ground.nonzero().squeeze(1)
    if ids.numel():
        at = lambda x: take_rows(x, ids)  # noqa: E731  (index_select: 3× faster than x[ids])
        p = at(air.origins) + at(air.ground)[:, None] * at(air.directions)
        atm = ctx.batch.atmosphere
        behind = behind.index_copy(0, ids, ground_radiance(p, at(air.sun_dir), at(air.sun), take(atm.ground, at(s)),
                                                           rows_of(air.air, ids), air.light_steps,
                                                           kernel=ctx.plan.joint.backend == "drjit"))
    t_end = torch.where(on_surface, surf.t if surf is not None else air.leave, air.leave)
    return behind * air.transmittance(rows, t_end), torch.where(ground, air.ground, torch.zeros_like(air.ground))


def on_the_ground(out: dict[str, Tensor], ground_t: Tensor, rays: Rays) -> dict[str, Tensor]:
    """The planet's ground is an opaque surface: alpha 1 where a ray ends on it (`ground_t` [n] > 0),
    and its distance and depth where nothing nearer set them."""
    ground = ground_t > 0
    out = {**out, "alpha": torch.where(ground, torch.ones_like(out["alpha"]), out["alpha"])}
    for key, t in (("distance", ground_t), ("depth", ground_t * rays.forward_cos),
                   ("depth_median", ground_t * rays.forward_cos)):
        out[key] = torch.where(ground & (out[key] == 0), t, out[key])  # the ground where nothing nearer
    return out


def camera_for(batch: Stacked) -> Camera:
    """The batch's cameras: given matrices, or look-at with a vertical field of view (45° where
    neither fov_y nor focal is given) or the seeds' focal length."""
    cam, image = batch.camera, batch.image
    if cam.matrix is not None:  # given matrices (e.g. the voxel seed's mirrored camera)
        return Camera(K=cam.matrix.K, world_to_camera=cam.matrix.world_to_camera, width=image.width, height=image.height)
    fov = torch.full_like(cam.roll, 45.0) if cam.fov_y is None and cam.focal is None else cam.fov_y
    return Camera.look_at(cam.eye, cam.target, cam.up, width=image.width, height=image.height, fov_y=fov,
                          focal=cam.focal, roll=cam.roll)


def resolve_into(out: Tensor, values: Tensor, key: str, spp: int) -> None:
    """A pixel's value from its sub-samples, written into `out` [C, p] (a channel-major buffer's
    columns): `values` [p, spp, C] resolved as the output resolves (`aovs.RESOLVE`: mean, the first
    sub-sample, or the mean over the sub-samples that hit)."""
    mode = RESOLVE[key]
    if mode == "first":  # ids do not average
        out.copy_(values[:, 0].T)
    elif spp == 1:  # the mean of one sub-sample, in one pass: x + 0 (−0 as +0, as the mean gave it)
        torch.add(values[:, 0].T, 0.0, out=out)  # a mean over a dim of one was ~0.5 ms an output of 65 k rays
    elif mode == "mean":
        out.copy_(values.mean(dim=1).T)
    else:
        out.copy_((values.sum(dim=1) / (values > 0).sum(dim=1).clamp_min(1)).T)


def check_options(*, seed, scenes: int, chunk_rays, dtype, device) -> tuple[list[int], torch.device]:
    """Refuses render's options unless valid for a batch of `scenes` scenes -> (one seed per
    scene, the torch device)."""
    integer("chunk_rays", chunk_rays, low=1)
    if dtype not in (None, torch.float32, torch.float64):
        fail("dtype", dtype, "expected torch.float32, torch.float64 or None (the quality level's)")
    try:
        device = torch.device(device)
        torch.empty(0, device=device)
    except (RuntimeError, TypeError, AssertionError) as err:
        fail("device", str(device), f"not a usable torch device here ({str(err).splitlines()[0]})")
    seeds = list(seed) if isinstance(seed, (list, tuple)) else [seed] * scenes
    if len(seeds) != scenes or not all(is_integer(x) for x in seeds):
        fail("seed", seed, f"expected an integer or one integer per scene ({scenes})")
    return seeds, device


def check_aovs(aovs: Sequence[str], scene) -> None:
    """Refuses `aovs` (render's argument) unless it is a list of AOV names that `scene` (a batch's
    first, levelled) can compute: ``sun_visibility`` needs the scene's sun."""
    if isinstance(aovs, str) or any(a not in RESOLVE for a in aovs):
        fail("aovs", aovs, "expected a list of AOV names from: " + ", ".join(sorted(RESOLVE)))
    if "sun_visibility" in aovs and sun_index(scene.lights) is None:
        fail("aovs", "sun_visibility", "needs lights[0] to be a sun (a directional light); this scene's lights: "
             f"{[li.kind for li in scene.lights]}")


def render(
    scene,
    *,
    seed: int | Sequence[int] = 0,
    device: str | torch.device = "cpu",
    dtype: torch.dtype | None = None,
    chunk_rays: int = DEFAULT_CHUNK_RAYS,
    compile: CompileMode | bool | None = "kernels",
    progress: Callable[[int], None] | None = None,
    aovs: Sequence[str] = (),
    keep_context: bool = False,
) -> RenderOutput:
    """Render a scene (or a list of scenes of one structure, as one batch).

    `scene`: a Scene, a dict, a .toml path or a preset name (or a list of those), or a prepared
    `renderer.prepare.Batch` (taken as it is). `seed` (one int, or one per scene) drives the dither
    and sub-pixel jitter, hashed per (seed, pixel, sample): a scene renders the same, to the bit,
    alone or anywhere in a batch and for any chunking. `dtype` defaults to the quality level's
    (float64 for reference). `chunk_rays` bounds peak memory. `compile` (`runtime.compilation`):
    "kernels" (True, the default) runs Dr.Jit's kernels wherever one renders a technique (the
    canonical output, within ~1e-5 of eager); "off" (False, None) is the eager reference.
    `stats["plan"]["marches"]` says what each march ran on.
    `progress(pixels)`, where given, is called after each chunk with the
    pixels it finished (in each of `image.passes` passes). With `image.passes` > 1,
    `stats["accumulation"]` is the mean |change| of the blended radiance after each pass after the
    first (`renderer.accumulate`). `aovs` asks for the AOVs computed only on request (the
    per-medium labels of `renderer.labels`: optical_thickness, alpha_volumes, instance,
    sun_visibility); the others are output wherever the scene computes them. `keep_context`:
    `RenderOutput.context` holds the render's `RenderContext` (its fields and lights), for code
    that evaluates the same scenes further (the dataset's volume labels). Every input is checked
    here, before anything renders."""
    batch = prepare(scene)
    seeds, device = check_options(seed=seed, scenes=len(batch), chunk_rays=chunk_rays, dtype=dtype, device=device)
    compile = compile_mode(compile)
    check_aovs(aovs, batch.scenes[0])
    start = time.perf_counter()
    # the plan reads shared values only
    plan = make_plan(stack(batch.scenes, dtype=torch.float64, device=device), tuple(aovs), compile=compile,
                     dtype=dtype, device=device)
    ctx = RenderContext(stack(batch.scenes, dtype=plan.dtype, device=device), plan, seeds=seeds, device=device)
    with glue_on_one_thread() if plan.threads == "glue_on_one_thread" else nullcontext():
        with ctx.timer.section("rays"):
            camera = camera_for(ctx.batch)
        buffers, acc = run_passes(ctx, camera, chunk_rays=chunk_rays, progress=progress)
        b, h, w = len(batch), ctx.batch.image.height, ctx.batch.image.width
        images = {k: v.view(-1, b, h, w).transpose(0, 1).contiguous() for k, v in buffers.items()}  # no copy when b = 1
        radiance, alpha, depth = images.pop("radiance"), images.pop("alpha"), images.pop("depth")
        image = post_process(ctx, radiance, images, View(camera=camera, sun=ctx.sun(), alpha=alpha))
    stats = render_stats(ctx, acc, rays=b * h * w * plan.spp, total_s=time.perf_counter() - start)
    return RenderOutput(image=image, radiance=radiance, depth=depth, alpha=alpha, aovs=images, camera=camera, stats=stats,
                        context=ctx if keep_context else None)


def run_passes(ctx: RenderContext, camera: Camera, *, chunk_rays: int,
               progress: Callable[[int], None] | None) -> tuple[dict[str, Tensor], Accumulator | None]:
    """Every chunk of the batch's pixels through `run_chunk`, once per accumulation pass ->
    ({output: (C, B·H·W) float32, channel-major}, the accumulator or None)."""
    plan = ctx.plan
    b, h, w, spp = len(ctx.batch), ctx.batch.image.height, ctx.batch.image.width, plan.spp
    pixels = b * h * w
    chunk_pixels = max(1, chunk_rays // spp)  # chunks hold whole pixels: sub-samples resolve in place
    keys = ["radiance", "alpha", "depth"] + [a for a in plan.aovs if a != "radiance"]
    acc = Accumulator(plan.blend, ctx.batch.image.blend_weight, h * w) if plan.passes > 1 else None
    scene_seeds = ctx.seeds
    for k in range(plan.passes):
        ctx.seeds = pass_seeds(scene_seeds, k)
        buffers: dict[str, Tensor] = {}
        for first in range(0, pixels, chunk_pixels):
            last = min(pixels, first + chunk_pixels)
            with ctx.timer.section("rays"):
                jitter = subpixel_jitter(first * spp, last * spp, seeds=ctx.seeds, width=w, height=h, spp=spp,
                                         dtype=ctx.dtype)
                # the rays' kernel where torch's glue runs on one thread (a worker, a kernel-only
                # render); on two, torch's rays were faster (65 k: 1.1 against 1.75 ms): the same bits
                rays = camera.ray_range(first * spp, last * spp, spp=spp, offsets=jitter,
                                        kernel=ctx.plan.kernels and torch.get_num_threads() == 1)
            values = run_chunk(ctx, rays)
            with ctx.timer.section("resolve") if spp > 1 else nullcontext():
                for key in keys:
                    value = values[key].to(torch.float32).reshape(last - first, spp, -1)
                    if key not in buffers:  # channel-major: for one scene the buffer already is (1, C, H, W)
                        buffers[key] = torch.empty(value.shape[2], pixels, dtype=torch.float32, device=value.device)
                    resolve_into(buffers[key][:, first:last], value, key, spp)
            if progress is not None:
                progress(last - first)
        if acc is not None:
            with ctx.timer.section("accumulate"):
                acc.add(buffers)
    return (acc.result() if acc is not None else buffers), acc


def render_stats(ctx: RenderContext, acc: Accumulator | None, *, rays: int, total_s: float) -> dict:
    """What the render records (`RenderOutput.stats`): the passes that ran and their times, the
    plan's decisions (`Plan.summary`), density evaluations, march steps and the render's counts."""
    plan = ctx.plan
    return {
        "passes": list(ctx.timer.seconds),
        "plan": plan.summary(),
        "density_evals": ctx.counts.density_evals,
        "density_evals_by_volume": {vol.plan.name: vol.field.evals for vol in ctx.volumes},
        "time_s": dict(ctx.timer.seconds),
        "total_s": total_s,
        "rays": rays,
        "march_steps": ctx.counts.march_steps,
        "truncated_rays": ctx.counts.truncated_rays,
        **({"error_estimate": ctx.counts.error_estimate} if plan.settings.tolerance is not None else {}),
        **({"voxel_steps": ctx.voxel_surface.steps_total} if plan.voxels is not None else {}),
        **({"accumulation": acc.changes} if acc is not None else {}),
        **({"path": path_stats(ctx.path_media)} if ctx.path_media is not None else {}),
        "dtype": str(ctx.dtype).removeprefix("torch."),
    }


def path_stats(media: path.Media) -> dict:
    """`stats["path"]`: what the paths did (`path.PathCounts`) and the volumes tracked against
    their macro cells' bounds (`local_majorants`, `volume/local_majorant.py`), by name."""
    local = [vol.plan.name for vol, table in zip(media.vols, media.local or []) if table is not None]
    return {**vars(media.counts), "local_majorants": local}


def post_process(ctx: RenderContext, radiance: Tensor, aovs: dict[str, Tensor], view: View) -> Tensor:
    """The plan's post effects on linear radiance (B, 3, H, W), in order -> the image in [0, 1];
    `view` goes to the effects that need the camera, sun and alpha."""
    x = radiance
    post = stack(ctx.batch.post.models, dtype=x.dtype, device=x.device)  # float32 images
    for kind, name in ctx.plan.post:
        effect = POST[kind]
        with ctx.timer.section(name):
            x = effect.fn(x, post, aovs, view) if effect.caps.get("view") else effect.fn(x, post, aovs)
    return x.clamp(0.0, 1.0)
