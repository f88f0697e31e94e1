"""The scene schema, validated once at the boundary; `load_scene` and `preset`.

Every model forbids unknown keys and non-finite numbers. Validation errors surface as one
`SceneError` (a ValueError) naming the key path, the value and what is allowed.
"""

from __future__ import annotations

import copy
import math
import tomllib
from pathlib import Path
from typing import Any, Literal, Mapping

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from pydantic_core import PydanticCustomError

from .validate import SceneError, did_you_mean, fail

Vec3 = tuple[float, float, float]
PRESET_DIR = Path(__file__).parent / "presets"


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, arbitrary_types_allowed=True, frozen=True)

    @model_validator(mode="before")
    @classmethod
    def _known_keys(cls, data: Any) -> Any:
        if isinstance(data, Mapping):
            for key in data:
                if key not in cls.model_fields:
                    allowed = ", ".join(cls.model_fields)
                    raise PydanticCustomError(
                        "unknown_key",
                        "unknown key{hint}; allowed keys: {allowed}",
                        {"key": str(key), "hint": did_you_mean(str(key), cls.model_fields), "allowed": allowed},
                    )
        return data


def _refuse(path: str, value: Any, allowed: str):
    """A cross-key rule broken: an error naming `path` (from the scene's root), not the model's."""
    raise PydanticCustomError("at_path", "{allowed}", {"path": path, "value": value, "allowed": allowed})


def _nonneg(v: Vec3, what: str = "components") -> Vec3:
    if min(v) < 0:
        raise ValueError(f"{what} must be >= 0")
    return v


class One(Strict):
    """A choice written as a table with exactly one key, e.g. ``{ box = {...} }``."""

    @model_validator(mode="after")
    def _exactly_one(self):
        given = [k for k in type(self).model_fields if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError(f"give exactly one of {', '.join(type(self).model_fields)}")
        return self

    @property
    def kind(self) -> str:
        return next(k for k in type(self).model_fields if getattr(self, k) is not None)

    @property
    def value(self) -> Any:
        return getattr(self, self.kind)


class Image(Strict):
    width: int = Field(256, ge=1, le=16384)
    height: int = Field(256, ge=1, le=16384)
    spp: int | None = Field(None, ge=1, le=1024, description="samples per pixel; None: the quality level's")


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
        return 45.0 if self.fov_y is None and self.focal is None else self.fov_y


class Glow(Strict):
    """An additive lobe around the sun: color · clamp(dot(sun, rd), 0, 1)^power."""

    color: Vec3
    power: float = Field(gt=0.0)
    _c = field_validator("color")(lambda v: _nonneg(v))


class Atmosphere(Strict):
    """Rayleigh + Mie single scattering around a spherical planet (lengths in world units; the
    defaults are Earth's in metres). The sun is the scene's first light."""

    planet_radius: float = Field(6.36e6, gt=0.0)
    atmosphere_height: float = Field(6.0e4, gt=0.0)
    eye_height: float = Field(1.0, ge=0.0)
    rayleigh: Vec3 = (5.8e-6, 13.5e-6, 33.1e-6)
    mie: float = Field(21e-6, ge=0.0)
    rayleigh_height: float = Field(7994.0, gt=0.0)
    mie_height: float = Field(1200.0, gt=0.0)
    mie_g: float = Field(0.76, gt=-1.0, lt=1.0)
    sun_intensity: float = Field(20.0, ge=0.0)
    steps: int | None = Field(None, ge=1, le=1024, description="None: the quality level's")
    light_steps: int | None = Field(None, ge=1, le=1024, description="None: the quality level's")
    _r = field_validator("rayleigh")(lambda v: _nonneg(v))

    @model_validator(mode="after")
    def _eye_inside(self):
        if self.eye_height >= self.atmosphere_height:
            raise ValueError("eye_height must be below atmosphere_height")
        return self


class Sky(Strict):
    kind: Literal["constant", "gradient", "atmosphere"] = "constant"
    atmosphere: Atmosphere = Field(default_factory=Atmosphere)
    radiance: Vec3 = (0.0, 0.0, 0.0)
    horizon: Vec3 = (0.675, 0.785, 0.825)  # gradient: colour at rd.y = 0
    slope: Vec3 = (0.2, 0.1, 0.2)  # gradient: colour = horizon − rd.y · slope
    halo: Glow | None = None  # added to the sky (seen through volumes)
    flare: Glow | None = None  # added over everything, after compositing
    _r = field_validator("radiance")(lambda v: _nonneg(v))


class Shadow(Strict):
    """How a sun's transmittance through the volumes is found: `march` (a shadow march from every lit
    sample) or `grid` (optical depth tabulated once per scene on `resolution`² × (resolution/2 + 1)
    sun-aligned nodes over each volume's bounds (Simpson's rule along the sun), looked up bicubically
    across the sun plus a trapezoid over the gap to the next plane: far cheaper; box and sphere
    bounds only). Measured on the Mitsuba parity cloud (64³ grid, optical depth 10) at 256², 96
    steps, against the exact float64 reference: relative RMSE 0.093% with the grid at resolution 128
    (0.026% is the primary march's alone) in 0.27 s, where a 32-step shadow march takes 1.2 s for
    0.12% at 64 steps. Hard surfaces of the medium (a dense field cut by sphere bounds) smear over
    a grid cell: 1.9%, 0.69%, 0.30% relative RMSE against the march at resolution 96, 192, 384 on
    such a sphere."""

    method: Literal["march", "grid"] = "march"
    steps: int | None = Field(None, ge=1, le=4096, description="None: the quality level's")
    growth: float = Field(1.0, ge=1.0, le=4.0)
    first_step: float | None = Field(None, gt=0.0)
    resolution: int = Field(128, ge=4, le=1024)


class Light(Strict):
    kind: Literal["sun"] = "sun"
    direction: Vec3 = (1.0, 1.0, -0.5)
    color: Vec3 = (1.0, 1.0, 1.0)
    intensity: float = Field(1.0, ge=0.0)
    shadow: Shadow | None = None

    @field_validator("direction")
    @classmethod
    def _nonzero(cls, v):
        if math.hypot(*v) < 1e-12:
            raise ValueError("direction must be a non-zero vector (it points towards the sun)")
        return v

    _c = field_validator("color")(lambda v: _nonneg(v))


class Box(Strict):
    min: Vec3 = (-0.5, -0.5, -0.5)
    max: Vec3 = (0.5, 0.5, 0.5)

    @model_validator(mode="after")
    def _ordered(self):
        if any(hi <= lo for lo, hi in zip(self.min, self.max)):
            raise ValueError(f"max {self.max} must exceed min {self.min} on every axis")
        return self


class Sphere(Strict):
    center: Vec3 = (0.0, 0.0, 0.0)
    radius: float = Field(1.0, gt=0.0)


class Slab(Strict):
    y_min: float = -1.0
    y_max: float = 1.0

    @model_validator(mode="after")
    def _ordered(self):
        if self.y_max <= self.y_min:
            raise ValueError(f"y_max {self.y_max} must exceed y_min {self.y_min}")
        return self


class Bounds(One):
    box: Box | None = None
    sphere: Sphere | None = None
    slab: Slab | None = None


class GridSource(Strict):
    """A 3D array given as `path` (a .npy file) or `data` (an array or tensor), indexed [k, j, i]."""

    path: str | None = None
    data: Any = None

    def _check(self, array: np.ndarray) -> np.ndarray:
        """Subclasses: validate the values and return the stored array."""
        raise NotImplementedError

    @model_validator(mode="after")
    def _load(self):
        if (self.path is None) == (self.data is None):
            raise ValueError("give path (a .npy file) or data (an array), not both")
        if self.path is not None:
            if not Path(self.path).is_file():
                raise ValueError(f"no such file: {self.path}")
            array = np.load(self.path)
        else:
            array = np.asarray(self.data.numpy() if hasattr(self.data, "numpy") else self.data)
        if array.ndim != 3 or min(array.shape) < 1:
            raise ValueError(f"grid must be a 3D array [k, j, i], got shape {array.shape}")
        object.__setattr__(self, "data", self._check(array))
        return self


class GridDensity(GridSource):
    """grid[k, j, i] is the value at the centre of cell (i, j, k) of the volume's box."""

    def _check(self, array: np.ndarray) -> np.ndarray:
        if not np.issubdtype(array.dtype, np.number) or not np.all(np.isfinite(array)) or array.min() < 0:
            raise ValueError("grid values must be finite numbers >= 0")
        return array.astype(np.float64, copy=False)


class FbmDensity(Strict):
    """density = max(bias + amplitude · fbm(frequency · (p − wind·time) + offset) − radial·|p − center|, 0):
    `radial` > 0 thins the noise out away from `center` (a puff instead of a filled bound)."""

    octaves: int = Field(5, ge=1, le=12)
    frequency: float = Field(1.0, gt=0.0, le=1e6)
    noise: Literal["value", "perlin", "worley"] = "value"
    seed: int = 0
    amplitude: float = 1.0
    bias: float = 0.0
    offset: Vec3 = (0.0, 0.0, 0.0)
    wind: Vec3 = (0.0, 0.0, 0.0)
    radial: float = Field(0.0, ge=0.0)
    center: Vec3 = (0.0, 0.0, 0.0)


class CloudsDensity(Strict):
    """The seed template's cloud layer `map()`:
    clamp(bias − p.y + density_scale · fbm(p − wind·time), 0, 1), fbm of texture noise in [−1, 1]."""

    texture_seed: int = 0
    texture: Any = None  # a PNG path or a uint8 array (256, 256, 4) [y, x, channel]
    octaves: int = Field(5, ge=1, le=5)
    density_scale: float = 1.75
    bias: float = -0.5
    wind: Vec3 = (0.0, 0.1, 1.0)

    @field_validator("texture")
    @classmethod
    def _texture(cls, v):
        if v is None:
            return None
        if isinstance(v, (str, Path)):
            if not Path(v).is_file():
                raise ValueError(f"no such file: {v}")
            from PIL import Image as PILImage

            v = np.asarray(PILImage.open(v).convert("RGBA"))
        array = np.asarray(v)
        if array.shape != (256, 256, 4) or array.dtype != np.uint8:
            raise ValueError(f"noise texture must be uint8 (256, 256, 4), got {array.dtype} {array.shape}")
        return array


class ExponentialDensity(Strict):
    """density = value · e^{−(y − base)/scale_height}."""

    value: float = Field(1.0, ge=0.0)
    base: float = 0.0
    scale_height: float = Field(1.0, gt=0.0)


class Density(One):
    constant: float | None = Field(None, ge=0.0)
    grid: GridDensity | None = None
    exponential: ExponentialDensity | None = None
    fbm: FbmDensity | None = None
    clouds: CloudsDensity | None = None


class HG(Strict):
    g: float = Field(0.0, gt=-1.0, lt=1.0)


class DualHG(Strict):
    g_forward: float = Field(0.8, gt=-1.0, lt=1.0)
    g_backward: float = Field(-0.2, gt=-1.0, lt=1.0)
    weight: float = Field(0.5, ge=0.0, le=1.0)


class Empty(Strict):
    pass


class Phase(One):
    isotropic: Empty | None = None
    hg: HG | None = None
    dual_hg: DualHG | None = None
    rayleigh: Empty | None = None
    mie: HG | None = None

    @model_validator(mode="before")
    @classmethod
    def _shorthand(cls, data):
        return {data: {}} if isinstance(data, str) else data


class ShaderLook(Strict):
    """The seeds' non-physical look (shading = "shader"): alpha = density·alpha_scale, colour =
    mix(color_lit, color_dark, density) · (sun_color · derivative light + ambient), fog towards the sky."""

    light: Literal["derivative", "none"] = "derivative"
    light_offset: float = Field(0.3, gt=0.0)
    light_scale: float = Field(0.6, gt=0.0)
    ambient: Vec3 = (0.91, 0.98, 1.05)
    # height gradient (seed Step 6 Method C): ambient = mix(ambient, ambient_top, normalised height
    # in the bounds); e.g. ambient = [0.229, 0.394, 0.512], ambient_top = [0.876, 0.982, 1.176]
    ambient_top: Vec3 | None = None
    color_lit: Vec3 = (1.0, 0.95, 0.8)
    color_dark: Vec3 = (0.25, 0.3, 0.35)
    alpha_scale: float = Field(0.4, ge=0.0)
    fog: float = Field(0.0, ge=0.0)  # mix towards the sky by 1 − exp(−fog·t²)


class Volume(Strict):
    bounds: Bounds = Field(default_factory=lambda: Bounds(box=Box()))
    density: Density = Field(default_factory=lambda: Density(constant=1.0))
    sigma_t: float = Field(1.0, ge=0.0, le=1e12)
    albedo: float = Field(1.0, ge=0.0, le=1.0)
    emission: Vec3 = (0.0, 0.0, 0.0)
    phase: Phase = Field(default_factory=lambda: Phase(isotropic=Empty()))
    shading: Literal["physical", "shader"] = "physical"
    shader: ShaderLook = Field(default_factory=ShaderLook)
    _e = field_validator("emission")(lambda v: _nonneg(v))

    @model_validator(mode="after")
    def _grid_needs_box(self):
        if self.density.kind == "grid" and self.bounds.kind != "box":
            raise ValueError("a grid density needs box bounds (the grid spans the box)")
        return self


class Lod(Strict):
    """Octaves at distance t: octaves − floor(log2(1 + scale·t)) (the template's LOD)."""

    scale: float = Field(0.5, gt=0.0)


class March(Strict):
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


class Fog(Strict):
    color: Vec3 = (0.5, 0.6, 0.7)
    density: float = Field(0.01, ge=0.0)
    _c = field_validator("color")(lambda v: _nonneg(v))


class Post(Strict):
    tonemap: Literal["none", "smoothstep", "reinhard", "aces"] = "none"
    exposure: float = Field(1.0, gt=0.0)
    smoothstep_edges: tuple[float, float] = (0.15, 1.1)
    vignette: float = Field(0.0, ge=0.0, le=1.0)
    fog: Fog | None = None

    @field_validator("smoothstep_edges")
    @classmethod
    def _edges(cls, v):
        if v[1] <= v[0]:
            raise ValueError("smoothstep_edges must be increasing")
        return v


# ---------------------------------------------------------------------------------------------
# Voxels (see docs/VOXELS.md)

Int3 = tuple[int, int, int]


class SdfSphere(Strict):
    center: Vec3 = (0.0, 0.0, 0.0)
    radius: float = Field(1.0, gt=0.0)


class SdfBox(Strict):
    center: Vec3 = (0.0, 0.0, 0.0)
    half_size: Vec3 = (1.0, 1.0, 1.0)
    _h = field_validator("half_size")(lambda v: _nonneg(v))


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


class TerrainOccupancy(Strict):
    """Heightmap h(x, z) = base + amplitude · Σ_k gain^k · value_noise(frequency · lacunarity^k · (x, z));
    cell (i, j, k) with j > h is air, else grass (j > h − 1), dirt (j > h − 1 − dirt_depth), stone."""

    seed: int = 0
    base: float = 0.0
    amplitude: float = Field(8.0, ge=0.0)
    frequency: float = Field(0.05, gt=0.0)
    octaves: int = Field(4, ge=1, le=12)
    gain: float = Field(0.5, gt=0.0, le=1.0)
    lacunarity: float = Field(2.0, gt=0.0)
    dirt_depth: float = Field(3.0, ge=0.0)
    materials: Int3 = (1, 2, 3)  # grass, dirt, stone ids


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


class VoxelTexture(Strict):
    """Atlas (H, W, 3|4) uint8 (or a PNG path) of tiles × tiles tiles; material m uses tile m − 1
    (row-major from the top left), sampled at the face UV (nearest texel)."""

    atlas: Any
    tiles: int = Field(4, ge=1, le=256)

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
    seed: int = 0
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
    occupancy: Occupancy
    cells: CellRange = Field(default_factory=CellRange)
    origin: Vec3 = (0.0, 0.0, 0.0)  # world position of cell (0, 0, 0)'s min corner
    voxel_size: float = Field(1.0, gt=0.0)
    max_steps: int | None = Field(None, ge=1, le=1_000_000, description="None: the quality level's")
    traversal: Literal["dda", "hybrid"] = "dda"
    materials: list[Vec3] = Field(default_factory=lambda: [(1.0, 1.0, 1.0)], min_length=1, max_length=255)
    face_tones: Vec3 = (0.5, 1.0, 0.75)  # x, y, z faces (seed Step 5); [1, 1, 1] turns it off
    ambient: Vec3 = (0.3, 0.3, 0.3)
    ao: VoxelAO | None = None
    shadow: VoxelShadow | None = None
    texture: VoxelTexture | None = None
    glow: VoxelGlow | None = None
    rounded: VoxelRounded | None = None
    fog: VoxelFog | None = None

    @model_validator(mode="after")
    def _consistent(self):
        if self.glow is not None and self.occupancy.kind != "sdf":
            raise ValueError("glow needs an sdf occupancy (it accumulates the sdf distance)")
        return self


class Scene(Strict):
    time: float = 0.0
    image: Image = Field(default_factory=Image)
    camera: CameraSpec = Field(default_factory=CameraSpec)
    sky: Sky | None = None
    lights: list[Light] = Field(default_factory=list)
    volumes: list[Volume] = Field(default_factory=list)
    voxels: Voxels | None = None
    march: March = Field(default_factory=March)
    post: Post = Field(default_factory=Post)

    @model_validator(mode="after")
    def _shadow_grid_needs_finite_bounds(self):
        for l, light in enumerate(self.lights):
            if light.shadow is not None and light.shadow.method == "grid":
                for v, vol in enumerate(self.volumes):
                    if vol.bounds.kind == "slab":
                        _refuse(f"lights[{l}].shadow.method", "grid",
                                f"'grid' needs box or sphere bounds and volumes[{v}] is a slab (use 'march')")
        return self

    @model_validator(mode="after")
    def _atmosphere_needs_a_sun(self):
        if self.sky is not None and self.sky.kind == "atmosphere" and not self.lights:
            _refuse("sky.kind", "atmosphere", "the atmosphere is lit by the first light: add a [[lights]] sun")
        return self


# ---------------------------------------------------------------------------------------------
# Loading


def _path_str(loc: tuple) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


def _lookup(data: Any, loc: tuple) -> Any:
    for part in loc:
        try:
            data = data[part]
        except (KeyError, IndexError, TypeError):
            return None
    return data


def _scene_error(err: ValidationError, raw: Any) -> SceneError:
    """Turn pydantic's first error into our one message shape."""
    e = err.errors(include_url=False)[0]
    loc = tuple(p for p in e["loc"] if not (isinstance(p, str) and ("[" in p or p.startswith("function-"))))
    if e["type"] == "at_path":
        return SceneError(e["ctx"]["path"], e["ctx"]["value"], e["msg"])
    if e["type"] == "unknown_key":
        key = e["ctx"]["key"]
        loc = loc + (key,)
        return SceneError(_path_str(loc), _lookup(raw, loc), e["msg"])
    value = e.get("input")
    msg = e["msg"].removeprefix("Value error, ")
    if isinstance(value, Mapping) and len(repr(value)) > 120:
        value = f"{{{', '.join(map(str, value))}}}"
    return SceneError(_path_str(loc), value, msg)


def _set_path(data: dict, dotted: str, value: Any) -> None:
    """Apply one override ``a.b[0].c`` / ``a.b.0.c`` to a nested dict/list, creating tables."""
    parts = [p for p in dotted.replace("[", ".").replace("]", "").split(".") if p]
    if not parts:
        fail(dotted, value, "an override key must be a dotted path like 'camera.fov_y'")
    node: Any = data
    for i, part in enumerate(parts):
        last = i == len(parts) - 1
        if isinstance(node, list):
            if not part.isdigit() or int(part) >= len(node):
                where = _path_str(tuple(int(p) if p.isdigit() else p for p in parts[: i + 1]))
                fail(where, value, f"index out of range (the list has {len(node)} items)")
            part = int(part)
        elif not isinstance(node, dict):
            fail(dotted, value, f"{'.'.join(parts[:i])} is not a table")
        if last:
            node[part] = value
        else:
            if isinstance(node, dict) and part not in node:
                node[part] = {}
            node = node[part]


def parse_value(text: str) -> Any:
    """A command-line value: TOML syntax where it parses (numbers, [1,2,3], true), else a string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


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
        _set_path(data, key, value)
    return validate_scene(data)


def preset_names() -> list[str]:
    return sorted(p.stem for p in PRESET_DIR.glob("*.toml"))


def preset(name: str, **params: Any) -> Scene:
    """A bundled scene with its documented parameters (see `torchvol.presets`)."""
    from .presets import preset_dict

    if name not in preset_names():
        fail("preset", name, "unknown preset; available: " + ", ".join(preset_names()) + did_you_mean(name, preset_names()))
    return validate_scene(preset_dict(name, **params))
