"""A batch of scenes -> the plan: the passes it calls for, as data, and nothing else.

Every decision is made here, once: which strategy integrates each volume (closed form, fixed march,
fixed march over the occupied span, error-controlled march), which lights shade it and how their
shadows are found, which voxel passes run, which post effects apply. `render` executes the plan by
looking each pass up, and decides nothing again. A term the batch does not ask for is not in the
plan and costs nothing: no shadow pass without a light with `shadow`, no sky pass without `[sky]`,
no air march without `[atmosphere]`, no march without volumes, no post pass at its
identity setting.

Decisions read only values a batch shares (its structure), or ask whether *any* scene of the batch
needs a term (an effect at its identity setting gives the scene that does not need it the same
image, to the bit).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal

import torch

from ..fields import DENSITIES
from ..geometry.bounds import BOUNDS, SLAB_REACH
from ..light.lights import LIGHTS, Shadow, sun_index
from ..light.sky import SKIES
from ..post import POST
from ..runtime import compilation
from ..runtime.compilation import CompileMode
from ..scene.model import Scene
from ..scene.quality import QUALITY, MarchSettings, at_level, march_settings
from ..schema.batch import Stacked, stack
from ..volume import kernel_march
from ..volume.density_lanes import has_lanes
from ..volume.march import COMPACT_BELOW
from ..volume.shading import SHADINGS
from ..voxel.materials import any_ggx
from .aovs import produced

Strategy = Literal["closed_form", "march", "skip", "tolerance"]
# what a volume's march (or the voxel walk) runs on: no march (its closed form), eager torch, or one
# Dr.Jit kernel (`volume.kernel_march`, `voxel.walk`)
Backend = Literal["closed_form", "eager", "drjit"]
# torch's threads during a render: the caller's, or one for torch's ops while the Dr.Jit kernel
# runs on the caller's count (`runtime.threads.glue_on_one_thread`)
Threads = Literal["caller", "glue_on_one_thread"]


@dataclass(frozen=True)
class LightPass:
    """Light `light` shading a volume, the voxels or the terrain (None: the sky, a visibility ray
    of sky light: `volumes[i].ambient`, the terrain's `ambient`); `name` is its own pass in `stats`
    (its shadow, or the shader look's derivative light; None: no pass of its own); `shadow` its
    shadow settings (None: unshadowed). A shadow ray also sees the other volumes `occluders` (each
    its own pass `{name}.volume{j}`, whatever its shading), where `terrain`, the terrain
    (`{name}.terrain`) and, where `voxels`, the voxels (`{name}.voxels`)."""

    light: int | None
    name: str | None
    shadow: object | None
    occluders: tuple[int, ...] = ()
    terrain: bool = False
    voxels: bool = False

    def names(self) -> list[str]:
        """Its passes in `stats`, in the order they run: its own, the terrain, the voxels, then one
        per occluding volume (marched only where the terrain and the voxels let light through)."""
        if self.name is None:
            return []
        return ([self.name] + ([f"{self.name}.terrain"] if self.terrain else []) + ([f"{self.name}.voxels"] if self.voxels else [])
                + [f"{self.name}.volume{j}" for j in self.occluders])


@dataclass(frozen=True)
class VolumePass:
    index: int
    name: str  # "volume0"
    strategy: Strategy
    shading: str
    lights: tuple[LightPass, ...]
    emissive: bool  # some scene of the batch emits
    emission_map: str | None  # the emission colour map's kind (volume.emission), None: none
    bloom: int | None  # the point light the seeds' glow surrounds, None: no glow
    reach: float  # how far a ray or shadow ray travels in the volume (`march.max_distance`, or its bounds')
    compact_below: float  # the march drops finished rays below this active fraction (`volume.march.march`)
    sky_blend: bool = False  # sources blend into the sky with distance (`volumes[i].sky_blend`)
    ambient: bool = False  # sky light in-scattered (`volumes[i].ambient`)
    # its visibility march ("volume0.ambient"), through the other volumes and the terrain too
    ambient_sky: LightPass | None = None
    multiple: bool = False  # Wrenninge's octaves on the lights' in-scatter (`volumes[i].multiple_scattering`)
    # its optical depth along a line has a closed form (`fields.DENSITIES`' ``optical_depth``, no
    # edge fade): every shadow and sky ray through it takes that, exact, whatever `shadow.method`
    line_integral: bool = False
    backend: Backend = "eager"  # what its march runs on
    eager_because: str | None = None  # why it is eager where it is (`march_backend`)
    joint: bool = False  # marched with the other media in the scene's joint pass (`JointPass`), not on its own

    @property
    def step_pass(self) -> str:
        """The name of its integration pass: `volume{i}.closed_form` or `volume{i}.march`."""
        return f"{self.name}.closed_form" if self.strategy == "closed_form" else f"{self.name}.march"

    @property
    def ambient_pass(self) -> str | None:
        """The name of its ambient visibility march (None: no march, V = 1)."""
        return None if self.ambient_sky is None else self.ambient_sky.name

    @property
    def skip_pass(self) -> str:
        """The name of its empty-space skipping pass."""
        return f"{self.name}.skip"

    @property
    def emission_pass(self) -> str:
        """The name of its emission colour map's pass."""
        return f"{self.name}.emission_map"

    @property
    def bloom_pass(self) -> str:
        """The name of its bloom (the glow around a point light) pass."""
        return f"{self.name}.bloom"

    @property
    def sample_passes(self) -> list[str]:
        """The passes its march runs at the samples, in the order they first run there: the lights'
        shadows, the sky's visibility, the emission map, the bloom (a Dr.Jit kernel runs them
        inside its march and lists them there)."""
        return ([n for li in self.lights for n in li.names()] + (self.ambient_sky.names() if self.ambient_sky else [])
                + ([self.emission_pass] if self.emission_map is not None else [])
                + ([self.bloom_pass] if self.bloom is not None else []))

    def names(self) -> list[str]:
        """Its passes in `stats`, in the order they first run."""
        own = ([self.emission_pass] if self.emission_map is not None else []) + ([self.bloom_pass] if self.bloom is not None else [])
        own += [n for li in self.lights for n in li.names()] + (self.ambient_sky.names() if self.ambient_sky else [])
        return ([self.skip_pass] if self.strategy == "skip" else []) + ([] if self.joint else [self.step_pass]) + own


@dataclass(frozen=True)
class JointPass:
    """The physically shaded volumes (`volumes`, their indices) and the `[atmosphere]`'s air
    (`air`) marched together, one march through every medium of a ray (`volume.joint`): its pass
    `name` (``media.closed_form`` where every one has a closed form, else ``media.march``) and
    whether the labels need each medium's share of the alpha (`shares`)."""

    volumes: tuple[int, ...]
    name: str
    shares: bool = False
    air: bool = False
    backend: Backend = "eager"  # "drjit": the whole joint march is one kernel (`joint_backends`)


def joint_pass(volumes: tuple[VolumePass, ...], labels: LabelPass | None, *, air: bool) -> JointPass | None:
    """The joint march of the physically shaded volumes and the air, where there are two or more
    media, or the air (None: each volume is its own pass)."""
    members = tuple(v for v in volumes if SHADINGS[v.shading].caps["physical"])
    if len(members) < 2 and not air:
        return None
    closed = not air and all(v.strategy == "closed_form" for v in members)
    shares = labels is not None and bool({"alpha_volumes", "instance"} & set(labels.names))
    return JointPass(tuple(v.index for v in members), "media.closed_form" if closed else "media.march", shares, air)


def joint_backends(volumes: tuple[VolumePass, ...], joint: JointPass, *, air_kernel: bool) -> tuple[
        tuple[VolumePass, ...], JointPass]:
    """The volumes with their backends in the joint march, and the joint pass with its own: one
    Dr.Jit kernel marches every medium of a ray, the air too (where `air_kernel`: the render runs
    kernels, none error-controlled), where each member's march is one (`volume.kernel_march`);
    else the members march eagerly together, each saying why."""
    members = [volumes[i] for i in joint.volumes]
    slow = next((v for v in members if v.backend != "drjit"), None)
    if slow is None and (air_kernel or not joint.air):
        return volumes, replace(joint, backend="drjit")
    if not joint.air and all(v.backend == "closed_form" for v in members):
        return volumes, joint
    closed = "in closed form, which the kernel does not mix with marches"
    why = ("marched with the [atmosphere]'s air, which has no kernel here" if slow is None
           else f"marched with {slow.name} ({slow.eager_because or closed})")

    def because(v: VolumePass) -> str:  # a member with no kernel of its own says so
        return v.eager_because if v.backend == "eager" else closed if v.backend == "closed_form" else why

    return tuple(replace(v, backend="eager", eager_because=because(v)) if v.index in joint.volumes else v
                 for v in volumes), joint


@dataclass(frozen=True)
class VoxelPass:
    traversal: str  # "dda" or "hybrid"
    rounded: bool
    ao: bool
    shadows: tuple[LightPass, ...]  # one per light when `voxels.shadow` is set
    glow: bool  # glow and fog's extinction accumulate per visited cell, inside voxels.dda
    fog: bool  # its in-scattered light: voxels.fog, one shadow ray per distinct visited cell
    texture: bool
    emission: bool = False  # some material of some scene emits (voxels.materials[i].emission)
    water: bool = False  # the water plane's reflected and refracted rays (voxels.water)
    gi: bool = False  # voxels.gi: path-traced bounces (or cones) replace the ambient
    cone: bool = False  # voxels.gi.method = "cone": a mip chain and cones instead of paths
    ggx: bool = False  # some material of some scene is not Lambert (roughness < 1 or metallic > 0)
    reflections: int = 0  # bounces of mirror reflection rays (voxels.reflections)

    def names(self) -> list[str]:
        """The voxel surface's passes in `stats`, in the order they first run."""
        return (["voxels.dda"] + (["voxels.fog"] if self.fog else []) + (["voxels.rounded"] if self.rounded else []) + ["voxels.shade"]
                + (["voxels.ao"] if self.ao else [])
                + (["voxels.gi.mips", "voxels.gi.cones"] if self.cone else ["voxels.gi"] if self.gi else [])
                + [n for li in self.shadows for n in li.names()]
                + (["voxels.reflections"] if self.reflections else []) + (["voxels.water"] if self.water else []))


@dataclass(frozen=True)
class TerrainPass:
    shadows: tuple[LightPass, ...]  # one per light that casts shadows, seeing the terrain and every volume
    # the sky light's visibility ray (`terrain.ambient_visibility`) through every volume; None: constant
    sky: LightPass | None = None

    def names(self) -> list[str]:
        """The terrain's passes in `stats`: trace, shade, the sky light's visibility, then each light's shadow."""
        return (["terrain.trace", "terrain.shade"] + (self.sky.names() if self.sky else [])
                + [n for li in self.shadows for n in li.names()])


LABELS = ("optical_thickness", "alpha_volumes", "instance", "sun_visibility")


@dataclass(frozen=True)
class LabelPass:
    """The labels a batch computes (`names`, in `LABELS` order) and, for ``sun_visibility``, its
    shadow ray's `LightPass` (from lights[0], through every volume, the terrain and the voxels)."""

    names: tuple[str, ...]
    sun: LightPass | None = None

    def pass_names(self) -> list[str]:
        """The labels' passes in `stats`, in order (the sun ray's shadow passes for ``sun_visibility``)."""
        sun = [] if self.sun is None else self.sun.names()
        return [n for name in self.names for n in (sun if name == "sun_visibility" else [f"labels.{name}"])]


def label_pass(batch, requested) -> LabelPass | None:
    """The labels `requested` (AOV names) the batch computes, None if none (``sun_visibility``
    needs the scene's sun: `render` refuses it otherwise, `check_labels`)."""
    names = tuple(n for n in LABELS if n in requested and (n != "alpha_volumes" or batch.volumes))
    if not names:
        return None
    sun = None
    if "sun_visibility" in names:
        index = sun_index(batch.lights)
        shadow = batch.lights[index].shadow or Shadow(steps=QUALITY[batch.march.quality].shadow_steps)
        sun = LightPass(index, "labels.sun_visibility", shadow, shadow_occluders(batch), batch.terrain is not None,
                        batch.voxels is not None)
    return LabelPass(names, sun)


@dataclass(frozen=True)
class Plan:
    settings: MarchSettings
    sky: str | None  # the sky kind
    halo: bool
    flare: bool
    voxels: VoxelPass | None
    terrain: TerrainPass | None
    volumes: tuple[VolumePass, ...]
    joint: JointPass | None  # the volumes marched together (None: each on its own)
    atmosphere: bool  # the [atmosphere]'s air, a medium of the joint march (`JointPass.air`), and its ground
    spp: int
    post: tuple[tuple[str, str], ...]  # (POST kind, pass name), in order
    aovs: tuple[str, ...]  # the AOVs the render outputs
    passes: int = 1  # `image.passes`: > 1 accumulates (torchvol.renderer.accumulate)
    blend: str = "mean"
    labels: LabelPass | None = None  # the per-medium labels asked for (torchvol.renderer.labels), after the composite
    sun: int | None = None  # the index of the light that is the scene's sun (`lights.sun_index`), None: none
    compile: CompileMode = "off"  # the compile mode the render runs in (`runtime.compilation`)
    kernels: bool = False  # Dr.Jit's kernels run in this render: the mode is not "off", Dr.Jit runs for its dtype and device
    dtype: torch.dtype = torch.float32  # the render's float type (the quality level's unless given)
    threads: Threads = "caller"  # torch's thread policy during the render
    # what the voxel DDA walks run on: one Dr.Jit kernel (`voxel.walk.drjit_traverse`) wherever the
    # render runs kernels, else eagerly, the same bits either way (a walk with a per-cell callback,
    # the glow's, runs eagerly); None: no voxels
    walk: Backend | None = None
    # what a sky whose kind has a kernel (`SKIES`' ``kernel``: the atmosphere's per-pixel march) runs
    # on: "drjit" where the render runs kernels, else "eager"; None: no sky, or a kind with no march
    sky_backend: Backend | None = None
    path: tuple[int, int, Backend, str] | None = None  # `[path]`: (bounces, samples, the tracking's backend, single); None: no paths

    def summary(self) -> dict:
        """What the plan decided, JSON-safe (`stats["plan"]`): the passes in order, the sun, each
        march's backend (and, where one is eager, why: `eager_because`), the thread policy, the
        compile mode and the dtype."""
        eager = {v.name: v.eager_because for v in self.volumes if v.backend == "eager"}
        return {"passes": self.names(), "sun": self.sun, "marches": {v.name: v.backend for v in self.volumes},
                **({"eager_because": eager} if eager else {}),
                **({"joint": [self.volumes[v].name for v in self.joint.volumes]} if self.joint is not None else {}),
                **({"closed_form_shadows": closed} if (closed := [v.name for v in self.volumes if v.line_integral]) else {}),
                **({"air": self.joint.backend} if self.joint is not None and self.joint.air else {}),
                **({"walk": self.walk} if self.walk is not None else {}),
                **({"sky": self.sky_backend} if self.sky_backend is not None else {}),
                **({"path": dict(zip(("bounces", "samples", "backend", "single"), self.path))} if self.path else {}),
                "threads": self.threads, "compile": self.compile, "dtype": str(self.dtype).removeprefix("torch.")}

    def volume_names(self) -> list[str]:
        """The volumes' passes in the order they run: the joint march with its members' passes,
        then each other volume's."""
        joint = [] if self.joint is None else (["atmosphere"] if self.joint.air else []) + [self.joint.name] + [
            n for v in self.joint.volumes for n in self.volumes[v].names()]
        alone = [n for v in self.volumes if not v.joint for n in v.names()]
        return joint + alone

    def names(self) -> list[str]:
        """Every planned pass, in the order the render runs them (with both surfaces the terrain's
        first: the voxels see it behind them, `renderer.surfaces`)."""
        voxels, terrain = (self.voxels.names() if self.voxels else []), (self.terrain.names() if self.terrain else [])
        return (["rays"] + (["sky"] if self.sky else []) + (terrain + voxels if voxels and terrain else voxels + terrain)
                + self.volume_names() + ["composite"] + (["path"] if self.path else [])
                + (self.labels.pass_names() if self.labels else [])
                + (["post.flare"] if self.flare else [])
                + (["resolve"] if self.spp > 1 else []) + (["accumulate"] if self.passes > 1 else [])
                + [name for _, name in self.post])


def strategy(batch: Stacked, vol: Stacked, settings: MarchSettings) -> Strategy:
    """How volume `vol` (its `Stacked` parameters) of `batch` is integrated: in closed form (a
    homogeneous medium lit only by unshadowed suns, no term that varies along a ray), by the
    error-controlled march (`march.tolerance`), by a march over its occupied span only (a
    skippable density), or by the fixed march."""
    shading = SHADINGS[vol.shading]
    if not shading.caps["physical"]:
        return "march"
    lights = [LIGHTS[li.kind] for li in batch.lights]
    if (settings.closed_form and DENSITIES[vol.density.kind].caps.get("homogeneous") and settings.integrator != "alpha"
            and all(k.caps["directional"] for k in lights) and not any(li.shadow is not None for li in batch.lights)
            and all(term is None for term in (vol.sky_blend, vol.emission_map, vol.bloom, vol.edge, vol.ambient))):
        # (each of those terms varies along a ray)
        return "closed_form"  # the source is constant along a ray: one exact segment
    if settings.tolerance is not None:
        return "tolerance"
    if DENSITIES[vol.density.kind].caps.get("skippable") and settings.rule.placement in ("count", "size"):
        return "skip"
    return "march"


def shadow_occluders(batch: Stacked, *, exclude: int | None = None) -> tuple[int, ...]:
    """The volumes a shadow or sky-visibility ray sees besides the one it starts in (`exclude`):
    every one, whatever its shading (the extinction it casts is its `sigma_t` × density, the σ_t
    of the `optical_thickness` label)."""
    return tuple(j for j in range(len(batch.volumes)) if j != exclude)


def meets_terrain(batch: Stacked, v: int, light: int | None) -> bool:
    """Whether a shadow ray of volume `v` towards light `light` (None: the sky's, straight up) can
    meet the terrain in some scene of the batch. Not where the volume lies wholly above every
    height the terrain reaches (base + amplitude: its fbm stays inside (−1, 1)) and the ray never
    descends (the sky's; a sun's at or above the horizon; a point light's at or above that
    height): a ray that starts above a heightfield's top and never descends stays above it, so
    leaving the terrain out changes no value, and the rays skip its height there (6 octaves a
    shadow ray)."""
    if batch.terrain is None:
        return False
    t, vol = batch.terrain, batch.volumes[v]
    top = t.base + t.amplitude * (1.0 + 1e-3)  # clear of the tracer's slab padding and of rounding
    if not bool((BOUNDS[vol.bounds.kind].caps["lowest_y"](vol.bounds.value) > top + 1e-3).all()):
        return True
    if light is None:
        return False
    li = batch.lights[light]
    if LIGHTS[li.kind].caps["directional"]:
        return not bool((li.direction[:, 1] >= 0).all())
    return not bool((li.position[:, 1] > top + 1e-3).all())


def ambient_sky(batch: Stacked, v: int) -> LightPass | None:
    """The visibility march of volume `v`'s sky light (None: no ambient, or `visibility = "none"`):
    its own `ambient.steps` through itself, then through every other volume and the terrain."""
    amb = batch.volumes[v].ambient
    if amb is None or amb.visibility != "march":
        return None
    return LightPass(None, f"volume{v}.ambient", Shadow(steps=amb.steps), shadow_occluders(batch, exclude=v),
                     meets_terrain(batch, v, None), batch.voxels is not None)


def march_backend(batch: Stacked, vol: Stacked, strategy: Strategy, uses: tuple[LightPass, ...], *, compile: CompileMode,
                  settings: MarchSettings, dtype: torch.dtype, device: torch.device | str,
                  ambient: LightPass | None = None) -> tuple[Backend, str | None]:
    """What volume `vol`'s march runs on, decided once for the render, and why it is eager where
    it is (None otherwise): one Dr.Jit kernel (`volume.kernel_march`) wherever the compile mode is
    not "off", Dr.Jit runs for `dtype` on `device` (`compilation.drjit_available`) and the kernel
    renders the technique (`kernel_march.supports`); everything else eagerly."""
    if strategy == "closed_form":
        return "closed_form", None
    if compile == "off":
        return "eager", "compile is off: the eager reference"
    if strategy not in ("march", "skip"):
        return "eager", f"the {strategy} strategy has no kernel"
    if dtype != torch.float32 or torch.device(device).type != "cpu":
        return "eager", f"Dr.Jit renders float32 on the CPU, not {str(dtype).removeprefix('torch.')} on {torch.device(device).type}"
    if not compilation.drjit_available(dtype, device):
        return "eager", "Dr.Jit's LLVM backend is not available here"
    why = kernel_march.supports(batch, vol, uses, settings, ambient)
    return ("drjit", None) if why is None else ("eager", f"no kernel for {why}")


def volume_pass(batch: Stacked, v: int, settings: MarchSettings, *, compile: CompileMode = "off",
                dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> VolumePass:
    """The pass of volume `v` of `batch`: its strategy and backend, the lights it sees and their
    shadow passes, and the terms its source adds."""
    vol, name = batch.volumes[v], f"volume{v}"
    shading = SHADINGS[vol.shading]
    lights = list(enumerate(batch.lights)) if _lit_by_the_march(batch) else []
    if shading.caps["lights"] == "first":  # the shader look's derivative light
        uses = tuple(LightPass(l, f"{name}.derivative_light", None) for l, _ in lights[:1] if vol.shader.light == "derivative")
    elif shading.caps["lights"] == "unshadowed":  # lit inside the march pass, no shadow pass
        uses = tuple(LightPass(l, None, None) for l, _ in lights)
    else:
        occluders = shadow_occluders(batch, exclude=v)
        uses = tuple(LightPass(l, None, None) if li.shadow is None
                     else LightPass(l, f"{name}.shadow{l}", li.shadow, occluders, meets_terrain(batch, v, l),
                                    batch.voxels is not None)
                     for l, li in lights)
    bounds, density = BOUNDS[vol.bounds.kind], DENSITIES[vol.density.kind]
    if settings.max_distance is not None:
        reach = settings.max_distance
    else:  # a box's or sphere's exit is finite (far volumes stay visible); a slab's is not
        reach = math.inf if bounds.caps["finite"] else SLAB_REACH
    # a cheap sample (a trilinear lookup) costs less than compacting the batch; fbm octaves do not
    compact_below = COMPACT_BELOW if density.caps.get("cheap") else 1.0
    ambient = vol.ambient is not None
    how, sky = strategy(batch, vol, settings), ambient_sky(batch, v)
    backend, why = march_backend(batch, vol, how, uses, compile=compile, settings=settings, dtype=dtype, device=device,
                                 ambient=sky)
    return VolumePass(index=v, name=name, strategy=how, shading=vol.shading, lights=uses, backend=backend, eager_because=why,
                      emissive=bool((vol.emission > 0).any()), reach=reach, compact_below=compact_below,
                      emission_map=None if vol.emission_map is None else vol.emission_map.kind,
                      bloom=None if vol.bloom is None else vol.bloom.light,
                      sky_blend=vol.sky_blend is not None, ambient=ambient,
                      ambient_sky=sky,
                      multiple=vol.multiple_scattering is not None,
                      line_integral=density.caps.get("optical_depth") is not None and vol.edge is None)


def kernel_strategy(v: VolumePass, settings: MarchSettings) -> VolumePass:
    """Volume pass `v` with the skip dropped where the Dr.Jit kernel marches it alone by count
    placement: there the skipped march keeps the full march's step lattice, so skipping changes no
    sample but the empty ones (σ = 0), which cost the kernel less than the eager skip pass does
    (docs/VOLUMES.md, "Grid media"). Elsewhere the kernel skips as eager does: a joint march's
    pieces are the occupied spans, and size placement's step limit counts from the span's start."""
    if v.strategy == "skip" and v.backend == "drjit" and not v.joint and settings.rule.placement == "count":
        return replace(v, strategy="march")
    return v


def voxel_pass(batch: Stacked) -> VoxelPass | None:
    """The voxel surface's pass (None: no voxels): its traversal, the effects its scenes turn on and
    one shadow pass per light where `voxels.shadow` is set."""
    vx = batch.voxels
    if vx is None:
        return None
    # each shadow ray also meets every volume (`voxels.shadow{l}.volume{j}`, marched with the light's
    # own shadow settings or the quality level's steps: the voxels' DDA takes `voxels.shadow`) and
    # the terrain beside them
    shadows = tuple(LightPass(l, f"voxels.shadow{l}", li.shadow or Shadow(steps=QUALITY[batch.march.quality].shadow_steps),
                              shadow_occluders(batch), batch.terrain is not None)
                    for l, li in enumerate(batch.lights)) if vx.shadow is not None and _lit_by_the_march(batch) else ()
    return VoxelPass(traversal=vx.traversal, rounded=vx.rounded is not None, ao=vx.ao is not None, shadows=shadows,
                     glow=vx.glow is not None, fog=vx.fog is not None, texture=vx.texture is not None,
                     emission=any(bool((m.emission > 0).any()) for m in vx.materials),
                     water=vx.water is not None, gi=vx.gi is not None,
                     cone=vx.gi is not None and vx.gi.method == "cone", ggx=any_ggx(vx.materials),
                     reflections=vx.reflections.bounces if vx.reflections is not None and any_ggx(vx.materials) else 0)


def _lit_by_the_march(batch: Stacked) -> bool:
    """Whether the march's light counts: with `[path] single = "paths"` the paths give all of it,
    so the march runs unlit, for what the labels take (alpha, depth, the optical thickness), and
    its volumes', terrain's and voxels' shadow rays cost nothing."""
    return batch.path is None or batch.path.single != "paths"


def terrain_pass(batch: Stacked) -> TerrainPass | None:
    """The terrain's pass (None: no terrain), with a shadow pass per shadowed light that sees the
    terrain, every volume and the voxels (where the scene has them), and, where the scene has
    volumes, its sky light's visibility ray through them (`terrain.ambient_visibility`)."""
    if batch.terrain is None:
        return None
    terrain, sky = batch.terrain, None
    if not _lit_by_the_march(batch):
        return TerrainPass(shadows=(), sky=None)
    if terrain.ambient_visibility == "march" and batch.volumes:  # over no volume the sky is always seen
        sky = LightPass(None, "terrain.ambient", Shadow(steps=terrain.ambient_steps), shadow_occluders(batch),
                        voxels=batch.voxels is not None)
    return TerrainPass(shadows=tuple(LightPass(l, f"terrain.shadow{l}", li.shadow, shadow_occluders(batch), True,
                                               batch.voxels is not None)
                                     for l, li in enumerate(batch.lights) if li.shadow is not None), sky=sky)


def path_backend(batch: Stacked, kernels: bool, dtype: torch.dtype, device) -> Backend:
    """Where `[path]`'s tracking runs: Dr.Jit's kernel where the render runs kernels in float32 on
    the CPU and every volume's density and bounds are written in lanes, else eagerly."""
    lanes_everywhere = all(has_lanes(v) and "lanes" in BOUNDS[v.bounds.kind].caps for v in batch.volumes)
    cpu32 = dtype == torch.float32 and torch.device(device).type == "cpu"
    return "drjit" if kernels and cpu32 and lanes_everywhere else "eager"


def make_plan(batch: Stacked | Scene, aovs=(), *, compile: CompileMode = "off", dtype: torch.dtype | None = None,
              device: torch.device | str = "cpu") -> Plan:
    """The plan of a batch (a `Stacked` view of scenes at their quality level), or of one scene;
    `aovs`: AOV names asked for beyond those always output (the labels of `torchvol.renderer.labels`);
    `compile` (a resolved mode), `dtype` (None: the quality level's) and `device` decide which
    backend each march runs on and the thread policy."""
    if isinstance(batch, Scene):
        batch = stack([at_level(batch)])
    settings = march_settings(batch.march)
    dtype = dtype or settings.dtype
    voxels, terrain = voxel_pass(batch), terrain_pass(batch)  # both run before the volumes, which march up to them
    volumes = tuple(volume_pass(batch, v, settings, compile=compile, dtype=dtype, device=device)
                    for v in range(len(batch.volumes)))
    labels = label_pass(batch, aovs)
    joint = joint_pass(volumes, labels, air=batch.atmosphere is not None)
    # where every march is Dr.Jit's kernel on its own pool, torch's ops are glue: one thread
    kernels = compile != "off" and compilation.drjit_available(dtype, device)
    if joint is not None:
        air_kernel = kernels and dtype == torch.float32 and torch.device(device).type == "cpu" and settings.tolerance is None
        volumes, joint = joint_backends(tuple(replace(v, joint=v.index in joint.volumes) for v in volumes), joint,
                                        air_kernel=air_kernel)
    volumes = tuple(kernel_strategy(v, settings) for v in volumes)
    glue = voxels is None and terrain is None and bool(volumes) and all(v.backend == "drjit" for v in volumes)
    return Plan(
        settings=settings,
        sky=None if batch.sky is None else batch.sky.kind,
        halo=batch.sky is not None and batch.sky.halo is not None,
        flare=batch.sky is not None and batch.sky.flare is not None,
        voxels=voxels,
        terrain=terrain,
        volumes=volumes,
        joint=joint,
        atmosphere=batch.atmosphere is not None,
        spp=batch.image.spp,
        post=tuple((k.name, k.pass_name(batch.post)) for k in POST if k.active(batch.post)),
        aovs=tuple(produced(batch, aovs)),
        passes=batch.image.passes,
        blend=batch.image.blend,
        labels=labels,
        sun=sun_index(batch.lights),
        compile=compile,
        dtype=dtype,
        threads="glue_on_one_thread" if glue else "caller",
        walk=None if voxels is None else "drjit" if kernels else "eager",
        sky_backend=None if batch.sky is None or not SKIES[batch.sky.kind].caps.get("kernel") else
        "drjit" if kernels else "eager",
        kernels=kernels,
        path=None if batch.path is None else (batch.path.bounces, batch.path.samples, path_backend(batch, kernels, dtype, device),
                                              batch.path.single),
    )


__all__ = ["JointPass", "LightPass", "Plan", "TerrainPass", "VolumePass", "VoxelPass", "make_plan"]
