"""The scene schema, validated once at the boundary; `load_scene` and `preset`.

Every model forbids unknown keys and non-finite numbers (`torchvol.schema`). The technique tables
(bounds, density, phase, lights, sky) are built from the registries, so a registered kind is a
valid key. Validation errors surface as one `SceneError` (a ValueError) naming the key path, the
value and what is allowed. Each field's batch role (per scene or shared by a batch) is declared
here, beside its type (`torchvol.schema`).
"""

from __future__ import annotations

import copy
import math
from functools import lru_cache
from pathlib import Path
from typing import Annotated, Any, Literal, Mapping

import numpy as np
import tomllib
from pydantic import BaseModel, Field, ValidationError, field_validator, model_validator

from ..fields import DENSITIES
from ..fields.edge import Edge
from ..geometry.bounds import BOUNDS, Box
from ..light.atmosphere import AtmosphereMedium
from ..light.lights import LIGHTS, sun_index
from ..light.phase import PHASES, Empty, PhaseChoice
from ..light.sky import SKIES
from ..post import Post
from ..schema.keypath import lookup, path_str, set_path
from ..schema.models import (
    EACH,
    SHARED,
    GridSource,
    One,
    Strict,
    Vec3,
    nonneg,
    reachable_models,
    refuse,
)
from ..schema.validate import SceneError, did_you_mean, fail
from ..terrain import Terrain
from ..volume.ambient import Ambient
from ..volume.emission import Bloom, EmissionMap
from ..volume.multiple import MultipleScattering
from ..volume.shader_look import ShaderLook
from ..volume.shading import SHADINGS
from ..volume.surface_look import SurfaceLook
from ..voxel.cone import VoxelGIs
from ..voxel.materials import Material
from ..voxel.water import VoxelWater

PRESET_DIR = Path(__file__).parent / "presets"


class Image(Strict):
    width: int = Field(256, ge=1, le=16384)
    height: int = Field(256, ge=1, le=16384)
    spp: int | None = Field(None, ge=1, le=1024, description="samples per pixel; None: the quality level's")
    # progressive accumulation (torchvol.renderer.accumulate): passes with their own dither and jitter, blended
    passes: int = Field(1, ge=1, le=4096, description="passes blended into the image (1: a single render)")
    blend: Literal["mean", "exponential"] = "mean"  # running mean, or the seeds' mix(old, new, blend_weight)
    blend_weight: float = Field(0.05, gt=0.0, le=1.0)


class CameraMatrix(Strict):
    """A camera given by its matrices (OpenCV axes): K 3×3 in pixels, world_to_camera 4×4 rigid
    (orthonormal rotation; determinant −1 allowed: a mirrored camera such as the voxel seed's)."""

    K: tuple[Vec3, Vec3, Vec3]
    world_to_camera: tuple[tuple[float, float, float, float], ...]

    @model_validator(mode="after")
    def _valid(self):
        K = np.asarray(self.K, dtype=np.float64)
        if K[0, 0] <= 0 or K[1, 1] <= 0 or K[1, 0] != 0 or tuple(K[2]) != (0.0, 0.0, 1.0):
            raise ValueError("K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
        M = np.asarray(self.world_to_camera, dtype=np.float64)
        if M.shape != (4, 4) or tuple(M[3]) != (0.0, 0.0, 0.0, 1.0):
            raise ValueError("world_to_camera must be 4x4 with last row [0, 0, 0, 1]")
        R = M[:3, :3]
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-6:
            raise ValueError("world_to_camera's 3x3 block must be orthonormal")
        return self


class CameraSpec(Strict):
    eye: Vec3 = (0.0, 1.0, -5.0)
    target: Vec3 = (0.0, 0.0, 0.0)
    up: Vec3 = (0.0, 1.0, 0.0)
    fov_y: float | None = Field(None, gt=0.0, lt=180.0, description="full vertical field of view, degrees")
    focal: float | None = Field(None, gt=0.0, description="the seeds' shader focal length (fy = focal·H/2)")
    roll: float = 0.0
    matrix: CameraMatrix | None = None  # given: K and world_to_camera are used as they are

    @model_validator(mode="after")
    def _geometry(self):
        if self.fov_y is not None and self.focal is not None:
            raise ValueError("give fov_y or focal, not both")
        forward = np.subtract(self.target, self.eye)
        if np.linalg.norm(forward) < 1e-9:
            raise ValueError(f"eye {self.eye} equals target: no view direction")
        up = np.asarray(self.up)
        if np.linalg.norm(up) < 1e-9:
            raise ValueError("up must be a non-zero vector")
        cross = np.linalg.norm(np.cross(forward / np.linalg.norm(forward), up / np.linalg.norm(up)))
        if cross < 1e-6:
            raise ValueError("up is parallel to the view direction (target - eye)")
        return self

    @property
    def resolved_fov_y(self) -> float | None:
        """The vertical field of view in degrees: `fov_y`, 45 where neither it nor `focal` is given,
        None where `focal` is."""
        return 45.0 if self.fov_y is None and self.focal is None else self.fov_y


Bounds = BOUNDS.one_of("Bounds", "Where the medium is: `{ box = {...} }`, `{ sphere = {...} }` or `{ slab = {...} }`.")
Density = DENSITIES.one_of("Density", "The density field: one of the registered kinds, e.g. `{ fbm = {...} }`.")
Phase = PHASES.one_of("Phase", "The phase function: `{ hg = { g = 0.8 } }`, or a kind's name alone.", base=PhaseChoice)
Light = LIGHTS.tagged_union(default="sun")
Sky = SKIES.tagged_union(default="constant")
Shading = Literal[SHADINGS.names()]
_TAGS = set(LIGHTS.names()) | set(SKIES.names())  # the tables chosen by their `kind` key
_METHODS = {"path", "cone"}  # voxels.gi, chosen by its `method` key


class Volume(Strict):
    bounds: Bounds = Field(default_factory=lambda: Bounds(box=Box()))
    density: Density = Field(default_factory=lambda: Density(constant=1.0))
    sigma_t: float = Field(1.0, ge=0.0, le=1e12)
    albedo: float = Field(1.0, ge=0.0, le=1.0)
    emission: Vec3 = (0.0, 0.0, 0.0)
    emission_map: EmissionMap | None = None  # emitted radiance from a colour map (volume.emission)
    bloom: Bloom | None = None  # the seeds' artistic glow around a point light (volume.emission)
    phase: Phase = Field(default_factory=lambda: Phase(isotropic=Empty()))
    shading: Shading = "physical"
    shader: ShaderLook = Field(default_factory=ShaderLook)
    # the seeds' distance fog `mix(col, bg, 1 − exp(−k t²))` as a physical source term
    sky_blend: float | None = Field(None, gt=0.0, description="physical shading: each sample's source blends into the sky "
                                    "behind its ray by 1 − exp(−k·t²); None: no blend")
    # the realism terms (docs/VOLUMES.md): absent, physical shading is exactly single scattering
    edge: Edge | None = None
    ambient: Ambient | None = None
    multiple_scattering: MultipleScattering | None = None
    surface: SurfaceLook = Field(default_factory=SurfaceLook)  # shading = "surface" (the fur ball)
    _e = field_validator("emission")(lambda v: nonneg(v))

    @model_validator(mode="after")
    def _density_fits_bounds(self):
        if DENSITIES[self.density.kind].caps.get("needs_box") and self.bounds.kind != "box":
            raise ValueError(f"a {self.density.kind} density needs box bounds (it spans the box)")
        return self


class Lod(Strict):
    """Octaves at distance t: octaves − floor(log2(1 + scale·t)) (the template's LOD)."""

    scale: float = Field(0.5, gt=0.0)


class March(Strict):
    """How volumes are marched: accuracy settings, shared by a batch (one march per batch)."""

    quality: Literal["draft", "default", "high", "reference"] = "default"
    integrator: Literal["riemann", "frostbite", "alpha"] | None = None
    placement: Literal["count", "size", "adaptive"] | None = None
    steps: int | None = Field(None, ge=1, le=1_000_000)
    step_size: float | None = Field(None, gt=0.0)
    step_growth: float | None = Field(None, ge=0.0)  # adaptive: dt = max(step_size, step_growth·t)
    dither: Literal["none", "hash", "sin"] | None = None
    dither_scale: float | None = Field(None, ge=0.0)  # sin dither: t0 += dither_scale · hash(pixel)
    max_distance: float | None = Field(None, gt=0.0)
    min_transmittance: float | None = Field(None, ge=0.0, lt=1.0)
    density_threshold: float | None = Field(None, ge=0.0)
    lod: Lod | None = None
    closed_form: bool = True
    depth_threshold: float = Field(0.01, ge=0.0, le=1.0)
    # error-controlled marching: absolute on transmittance and on radiance relative to the light;
    # each ray picks its steps by step doubling (physical shading; replaces placement/steps); steps
    # never exceed half the density's feature size (a grid's cell, an fbm's finest octave), which
    # the estimate cannot see below, or span/steps for a density with none (exponential)
    tolerance: float | None = Field(None, gt=0.0, lt=1.0)

    @model_validator(mode="after")
    def _tolerance_integrator(self):
        if self.tolerance is not None and self.integrator == "alpha":
            raise ValueError("march.tolerance needs integrator riemann or frostbite")
        return self


# ---------------------------------------------------------------------------------------------
# Voxels (see docs/VOXELS.md)

Int3 = tuple[int, int, int]


class SdfSphere(Strict):
    center: Vec3 = (0.0, 0.0, 0.0)
    radius: float = Field(1.0, gt=0.0)


class SdfBox(Strict):
    center: Vec3 = (0.0, 0.0, 0.0)
    half_size: Vec3 = (1.0, 1.0, 1.0)
    _h = field_validator("half_size")(lambda v: nonneg(v))


class SdfRoundedBox(SdfBox):
    radius: float = Field(0.1, ge=0.0)


class SdfPair(Strict):
    a: "SdfNode"
    b: "SdfNode"


class SdfNode(One):
    """One SDF node: a primitive, or CSG over nodes (union/intersection lists, subtraction a − b)."""

    sphere: SdfSphere | None = None
    box: SdfBox | None = None
    rounded_box: SdfRoundedBox | None = None
    union: list["SdfNode"] | None = Field(None, min_length=1)
    intersection: list["SdfNode"] | None = Field(None, min_length=1)
    subtraction: SdfPair | None = None


SdfPair.model_rebuild()


class SdfOccupancy(Strict):
    """Cells whose centre (world) has sdf < 0 hold `material` (the seed's getVoxel)."""

    shape: SdfNode
    material: int = Field(1, ge=1, le=255)


class TerrainOres(Strict):
    """Sparse blocks of `material` in a terrain: a solid cell within `depth` of the surface (j > h − depth;
    1: the top layer) becomes `material` where hash3(cell, seed) < `density` (lamps, ores)."""

    material: int = Field(4, ge=1, le=255)
    density: float = Field(0.02, ge=0.0, le=1.0)
    seed: int = 0
    depth: float = Field(1.0, gt=0.0)


class TerrainOccupancy(Strict):
    """Heightmap h(x, z) = base + amplitude · Σ_k gain^k · value_noise(frequency · lacunarity^k · (x, z));
    cell (i, j, k) with j > h is air, else grass (j > h − 1), dirt (j > h − 1 − dirt_depth), stone;
    `ores` scatter a sparse material through the layers near the surface."""

    seed: int = 0
    base: float = 0.0
    amplitude: float = Field(8.0, ge=0.0)
    frequency: float = Field(0.05, gt=0.0)
    octaves: int = Field(4, ge=1, le=12)
    gain: float = Field(0.5, gt=0.0, le=1.0)
    lacunarity: float = Field(2.0, gt=0.0)
    dirt_depth: float = Field(3.0, ge=0.0)
    materials: Int3 = (1, 2, 3)  # grass, dirt, stone ids
    ores: TerrainOres | None = None


class GridOccupancy(GridSource):
    """grid[k, j, i] = material id (uint8, 0 empty) of cell (i, j, k) counted from `voxels.cells.min`."""

    def _check(self, array: np.ndarray) -> np.ndarray:
        if not np.issubdtype(array.dtype, np.integer) or array.min() < 0 or array.max() > 255:
            raise ValueError("grid values must be integer material ids in 0..255")
        return array.astype(np.uint8, copy=False)


class FunctionOccupancy(Strict):
    """A Python callable: cells [N, 3] (int64, i j k) -> material ids [N] (0 empty)."""

    fn: Any

    @field_validator("fn")
    @classmethod
    def _callable(cls, v):
        if not callable(v):
            raise ValueError("expected a callable mapping integer cells [N, 3] to material ids [N]")
        return v


class Occupancy(One):
    sdf: SdfOccupancy | None = None
    terrain: TerrainOccupancy | None = None
    grid: GridOccupancy | None = None
    function: FunctionOccupancy | None = None


class CellRange(Strict):
    """Integer cell range [min, max) covered by the voxel grid."""

    min: Int3 = (0, 0, 0)
    max: Int3 = (16, 16, 16)

    @model_validator(mode="after")
    def _ordered(self):
        if any(hi <= lo for lo, hi in zip(self.min, self.max)):
            raise ValueError(f"max {self.max} must exceed min {self.min} on every axis")
        if math.prod(hi - lo for lo, hi in zip(self.min, self.max)) > 2**30:
            raise ValueError("at most 2**30 cells")
        return self


class VoxelAO(Strict):
    """Neighbour AO (seed Step 7): ao = bilinear(vertex AO)^gamma."""

    gamma: float = Field(1.0, gt=0.0)


class VoxelShadow(Strict):
    """DDA shadow rays towards each sun from hit + offset·normal (seed Step 8)."""

    steps: int | None = Field(None, ge=1, le=100_000, description="None: the quality level's")
    offset: float = Field(0.01, ge=0.0)


class VoxelReflections(Strict):
    """Mirror reflection rays from each hit through the same DDA (seed 001 Variant 5), added with
    the Fresnel weight F · (1 − roughness)² (`voxel/passes/secondary.py`)."""

    bounces: int = Field(1, ge=1, le=4)
    steps: int = Field(64, ge=1, le=100_000)  # the seed's 64: fewer than the primary ray's


class VoxelTexture(Strict):
    """Atlas (H, W, 3|4) uint8 (or a PNG path) of tiles × tiles tiles, per scene; material m uses tile m − 1
    (row-major from the top left), sampled at the face UV (nearest texel)."""

    atlas: Annotated[Any, EACH]
    tiles: Annotated[int, EACH] = Field(4, ge=1, le=256)

    @field_validator("atlas")
    @classmethod
    def _atlas(cls, v):
        if isinstance(v, (str, Path)):
            if not Path(v).is_file():
                raise ValueError(f"no such file: {v}")
            from PIL import Image as PILImage

            v = np.asarray(PILImage.open(v).convert("RGB"))
        array = np.asarray(v.numpy() if hasattr(v, "numpy") else v)
        if array.ndim != 3 or array.shape[2] not in (3, 4) or array.dtype != np.uint8:
            raise ValueError(f"atlas must be uint8 (H, W, 3|4), got {array.dtype} {array.shape}")
        return array[..., :3]


class VoxelGlow(Strict):
    """Seed variant 1: glow += intensity / (epsilon + d²) per DDA step, d the sdf at the cell;
    radiance += glow · color. Needs an sdf occupancy."""

    intensity: float = Field(0.015, ge=0.0)
    epsilon: float = Field(0.01, gt=0.0)
    color: Vec3 = (0.4, 0.6, 1.0)


class VoxelRounded(Strict):
    """Seed variant 2: per-voxel rounded box of radius min + range · hash(cell), refined by `steps`
    SDF-march steps inside the hit voxel (converged where h < threshold)."""

    radius_min: float = Field(0.05, ge=0.0, le=0.5)
    radius_range: float = Field(0.35, ge=0.0, le=0.5)
    steps: int = Field(6, ge=1, le=64)
    threshold: float = Field(0.025, gt=0.0)
    seed: int = 0  # shared by a batch: the hash of each cell's radius
    retries: int = Field(8, ge=0, le=64)  # rays that miss a rounded voxel continue this many times


class VoxelFog(Strict):
    """Fog inside the DDA: per visited empty cell σ = density·e^{−(y − base)/scale_height}, in-scatter
    color · sun · shadow (a DDA shadow ray from the cell centre, `shadow_steps`) · e^{−τ}."""

    density: float = Field(0.05, ge=0.0)
    base: float = 0.0
    scale_height: float = Field(1e9, gt=0.0)
    color: Vec3 = (1.0, 1.0, 1.0)
    shadow_steps: int | None = Field(None, ge=1, le=10_000, description="None: the quality level's")


class Voxels(Strict):
    """A voxel world. Its occupancy and cell range are per scene (each scene's grid is built on its
    own); materials are per scene too, their count shared by a batch."""

    occupancy: Annotated[Occupancy, EACH]
    cells: Annotated[CellRange, EACH] = Field(default_factory=CellRange)
    origin: Vec3 = (0.0, 0.0, 0.0)  # world position of cell (0, 0, 0)'s min corner
    voxel_size: float = Field(1.0, gt=0.0)
    max_steps: int | None = Field(None, ge=1, le=1_000_000, description="None: the quality level's")
    traversal: Literal["dda", "hybrid"] = "dda"
    materials: list[Material] = Field(default_factory=lambda: [Material()], min_length=1, max_length=255,
                                      description="each a colour [r, g, b] or { color, roughness, metallic, emission }")
    face_tones: Vec3 = (0.5, 1.0, 0.75)  # x, y, z faces (seed Step 5); [1, 1, 1] turns it off
    ambient: Vec3 = (0.3, 0.3, 0.3)
    ao: VoxelAO | None = None
    shadow: VoxelShadow | None = None
    reflections: VoxelReflections | None = None
    texture: VoxelTexture | None = None
    glow: VoxelGlow | None = None
    rounded: VoxelRounded | None = None
    fog: VoxelFog | None = None
    water: VoxelWater | None = None
    gi: VoxelGIs | None = None  # path-traced diffuse bounces or cones (method), replacing `ambient`

    @model_validator(mode="after")
    def _consistent(self):
        if self.glow is not None and self.occupancy.kind != "sdf":
            raise ValueError("glow needs an sdf occupancy (it accumulates the sdf distance)")
        return self


class PathSettings(Strict):
    """`[path]`: the physical media path-traced with every order of scattering up to `bounces`
    scattering events a path (1: single scattering), `samples` paths a pixel (a sub-sample).
    `single`: "paths" (every order path-traced, unbiased) or "march" (the lights' single
    scattering, the emission and the background marched, noise-free, and the paths add the
    rest: the orders past the first and the sky's light scattered)."""

    bounces: int = Field(256, ge=1, le=100_000)
    samples: int = Field(64, ge=1, le=1_000_000)
    single: Literal["paths", "march"] = "paths"


# voxel keys whose look a path has no physical version of yet (`voxel.path_surface`)
PATH_REFUSED_VOXEL_KEYS = ("glow", "fog", "water")


def _voxels_a_path_traces(voxels) -> None:
    """Refuses, under `[path]`, the voxel keys a path cannot trace (faces of the materials' colour,
    GGX and emission, nothing else): each names its key."""
    for key in PATH_REFUSED_VOXEL_KEYS:
        if getattr(voxels, key) is not None:
            refuse(f"voxels.{key}", "<set>", "path tracing renders voxel faces of their materials' colour, "
                   "GGX and emission; remove it or [path]")


class Scene(Strict):
    time: float = 0.0
    image: Image = Field(default_factory=Image)
    camera: CameraSpec = Field(default_factory=CameraSpec)
    sky: Sky | None = None
    lights: list[Light] = Field(default_factory=list)
    volumes: list[Volume] = Field(default_factory=list)
    voxels: Voxels | None = None
    terrain: Terrain | None = None
    atmosphere: AtmosphereMedium | None = None  # the scene inside a planet's air (a medium of the march)
    march: Annotated[March, SHARED] = Field(default_factory=March)
    post: Post = Field(default_factory=Post)
    path: Annotated[PathSettings, SHARED] | None = None  # path-traced multiple scattering of the physical media

    @model_validator(mode="after")
    def _shadow_grid_needs_a_sun_and_finite_bounds(self):
        for l, light in enumerate(self.lights):
            if light.shadow is not None and light.shadow.method == "grid":
                if not LIGHTS[light.kind].caps["directional"]:
                    refuse(f"lights[{l}].shadow.method", "grid", f"'grid' tabulates a sun's shadow; a {light.kind} "
                           "light needs 'march'")
                for v, vol in enumerate(self.volumes):
                    if not BOUNDS[vol.bounds.kind].caps["finite"]:
                        refuse(f"lights[{l}].shadow.method", "grid",
                               f"'grid' needs box or sphere bounds and volumes[{v}] is a {vol.bounds.kind} (use 'march')")
        return self

    @model_validator(mode="after")
    def _path_traces_physical_media_alone(self):
        if self.path is None:
            return self
        if self.voxels is not None:
            _voxels_a_path_traces(self.voxels)
        for v, vol in enumerate(self.volumes):
            if vol.shading != "physical":
                refuse("path", "<path>", f"path tracing renders physical media; volumes[{v}].shading is {vol.shading!r}")
        return self

    @model_validator(mode="after")
    def _sky_lit_by_a_sun(self):
        if self.sky is None:
            return self
        sun = sun_index(self.lights) is not None
        if SKIES[self.sky.kind].caps.get("needs_sun") and not sun:
            refuse("sky.kind", self.sky.kind, "the atmosphere is lit by the first light: make lights[0] a sun")
        if self.atmosphere is not None:
            refuse("sky", "<sky>", "the [atmosphere] medium draws its own sky: remove [sky]")
        for glow in ("halo", "flare"):
            if getattr(self.sky, glow) is not None and not sun:
                refuse(f"sky.{glow}", "<glow>", f"the {glow} is a lobe around the sun: make lights[0] a sun")
        return self

    @model_validator(mode="after")
    def _bloom_around_a_point_light(self):
        for v, vol in enumerate(self.volumes):
            if vol.bloom is None:
                continue
            l = vol.bloom.light
            if l >= len(self.lights) or LIGHTS[self.lights[l].kind].caps["directional"]:
                refuse(f"volumes[{v}].bloom.light", l, f"the glow surrounds a point light: the index of one in lights "
                       f"(there are {len(self.lights)} lights)")
            if self.march.tolerance is not None:
                refuse("march.tolerance", self.march.tolerance, f"the error-controlled march steps over empty space, where "
                       f"volumes[{v}].bloom glows too: use a fixed march (steps) with bloom")
        return self

    @model_validator(mode="after")
    def _atmosphere_lit_by_a_sun(self):
        if self.atmosphere is not None and sun_index(self.lights) is None:
            refuse("atmosphere", "<atmosphere>", "the atmosphere is lit by the first light: make lights[0] a sun")
        return self

    @model_validator(mode="after")
    def _physical_terms(self):
        """Terms of the physical medium are refused, not ignored, under the shader look (which has
        shader.fog and shader.ambient)."""
        for v, vol in enumerate(self.volumes):
            if SHADINGS[vol.shading].caps["physical"]:
                continue
            for key in ("emission_map", "bloom", "sky_blend", "ambient", "multiple_scattering"):
                if getattr(vol, key) is not None:
                    refuse(f"volumes[{v}].{key}", "<set>", f"a term of the physical medium: it needs "
                           f"shading = 'physical' (volumes[{v}].shading is {vol.shading!r})")
        return self

    @model_validator(mode="after")
    def _ambient_from_a_sky(self):
        for v, vol in enumerate(self.volumes):
            if vol.ambient is not None and vol.ambient.radiance is None and self.sky is None:
                refuse(f"volumes[{v}].ambient.radiance", None, "no [sky] to take the ambient from: give radiance = [r, g, b] "
                       "or add a [sky]")
        return self

    @model_validator(mode="after")
    def _god_rays_need_a_sun(self):
        if self.post.god_rays is not None and sun_index(self.lights) is None:
            kind = self.lights[0].kind if self.lights else None
            refuse("post.god_rays", "<god_rays>", f"screen-space god rays radiate from the sun: make lights[0] a sun "
                   f"(lights[0] is {kind or 'absent'})")
        return self

    @model_validator(mode="after")
    def _keys_that_need_something_to_act_on(self):
        if self.post.fog is not None and not self.volumes and self.voxels is None and self.terrain is None:
            refuse("post.fog", "<fog>", "distance fog needs something to fog: add volumes, voxels or a terrain")
        if self.march.lod is not None and not any(DENSITIES[v.density.kind].caps.get("octaves") for v in self.volumes):
            refuse("march.lod", "<lod>", "no volume has a density with octaves to drop (fbm, clouds, explosion)")
        return self


# ---------------------------------------------------------------------------------------------
# Loading


def _scene_error(err: ValidationError, raw: Any) -> SceneError:
    """Turn pydantic's first error into our one message shape. A kind-tagged table's tag (e.g. a
    light's 'point') is left out of the path: it is the table's own `kind` value, not a key."""
    e = err.errors(include_url=False)[0]
    loc: tuple = ()
    for part in e["loc"]:
        if isinstance(part, str) and ("[" in part or part.startswith("function-")):
            continue
        node = lookup(raw, loc)
        if part in _TAGS and isinstance(node, Mapping) and part not in node and node.get("kind", part) == part:
            continue  # a tagged union's tag
        if part in _METHODS and isinstance(node, Mapping) and part not in node and node.get("method", "path") == part:
            continue
        loc = loc + (part,)
    if e["type"] == "at_path":
        return SceneError(e["ctx"]["path"], e["ctx"]["value"], e["msg"])
    if e["type"] == "union_tag_invalid":  # a `kind` no registry holds
        tag, allowed = e["ctx"]["tag"], [t.strip(" '") for t in e["ctx"]["expected_tags"].split(",")]
        key = "method" if isinstance(lookup(raw, loc), Mapping) and "method" in lookup(raw, loc) else "kind"
        return SceneError(path_str(loc + (key,)), tag, f"unknown {key}" + did_you_mean(tag, allowed)
                          + f"; {key}s: " + ", ".join(allowed))
    if e["type"] == "unknown_key":
        key = e["ctx"]["key"]
        loc = loc + (key,)
        return SceneError(path_str(loc), lookup(raw, loc), e["msg"])
    value = e.get("input")
    msg = e["msg"].removeprefix("Value error, ")
    if isinstance(value, Mapping) and len(repr(value)) > 120:
        value = f"{{{', '.join(map(str, value))}}}"
    return SceneError(path_str(loc), value, msg)


def read_source(source: str | Path | Mapping) -> dict:
    """A scene or recipe source as a plain dict: a .toml path, a preset name or a mapping."""
    if isinstance(source, BaseModel):
        return source.model_dump()
    if isinstance(source, Mapping):
        return copy.deepcopy(dict(source))
    path = Path(source)
    if path.suffix == ".toml" or path.exists():
        if not path.is_file():
            fail("source", str(source), "no such scene file")
        try:
            with open(path, "rb") as f:
                return tomllib.load(f)
        except tomllib.TOMLDecodeError as exc:
            fail("source", str(source), f"not valid TOML: {exc}")
    name = str(source)
    if (PRESET_DIR / f"{name}.toml").is_file():
        from .presets import preset_dict

        return preset_dict(name)
    fail("source", name, "expected a .toml path, a mapping or a preset name" + did_you_mean(name, preset_names()))


def validate_scene(data: Mapping) -> Scene:
    """A Scene from the dict `data`; a validation error is raised as one SceneError naming the key
    path."""
    try:
        return Scene.model_validate(data)
    except ValidationError as err:
        raise _scene_error(err, data) from None


def load_scene(source: str | Path | Mapping | Scene, overrides: Mapping[str, Any] | None = None) -> Scene:
    """A validated Scene from a .toml path, a preset name, a dict or a Scene; `overrides` maps
    dotted key paths to values (``{"camera.fov_y": 30}``)."""
    if isinstance(source, Scene) and not overrides:
        return source
    data = read_source(source)
    for key, value in (overrides or {}).items():
        set_path(data, key, value)
    return validate_scene(data)


@lru_cache(maxsize=1)
def schema_keys() -> frozenset[str]:
    """Every key any table of the scene schema may hold (recipes tell a scene's one-key table,
    e.g. `{ fbm = {...} }`, from a misspelt distribution by it)."""
    return frozenset(name for cls in reachable_models(Scene) for name in cls.model_fields)


def preset_names() -> list[str]:
    """The bundled presets' names, sorted."""
    return sorted(p.stem for p in PRESET_DIR.glob("*.toml"))


def preset(name: str, **params: Any) -> Scene:
    """A bundled scene with its documented parameters (see `torchvol.scene.presets`)."""
    from .presets import preset_dict

    if name not in preset_names():
        fail("preset", name, "unknown preset; available: " + ", ".join(preset_names()) + did_you_mean(name, preset_names()))
    return validate_scene(preset_dict(name, **params))
