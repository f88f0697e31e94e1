"""Extra outputs (AOVs): the `AOVS` registry, the one list of their names. Each is its function
`fn(batch (Stacked scene)) -> bool` (whether a scene of this structure computes it: only what was
computed is output) and its capabilities: ``channels`` (0: one per volume), ``resolve`` (how a pixel's sub-samples
combine: ``mean``, ``hit_mean`` (the mean over the sub-samples that hit something: depths) or
``first`` (ids, which do not average)), ``doc`` and ``on_request`` (computed only when asked for:
the per-medium labels of `torchvol.renderer.labels`)."""

from __future__ import annotations

from ..schema.registry import Registry
from ..voxel.cone import cone_ao
from ..voxel.materials import any_ggx

AOVS = Registry("aov")


def _aov(name: str, channels: int, resolve: str, produced, doc: str, on_request: bool = False) -> None:
    AOVS.register(name, None, produced, channels=channels, resolve=resolve, doc=doc, on_request=on_request)


_aov("radiance", 3, "mean", lambda batch: True, "linear radiance before post-processing")
# with volumes, or for distance fog (surfaces alone have no other depth than `depth`)
_aov("distance", 1, "hit_mean", lambda batch: bool(batch.volumes) or batch.post.fog is not None,
     "expected ray distance of what the ray hit (world units; 0: nothing)")
_aov("depth_median", 1, "hit_mean", lambda batch: bool(batch.volumes), "planar depth where transmittance crosses 0.5 (0: never)")
_aov("normal", 3, "mean", lambda batch: batch.voxels is not None or batch.terrain is not None,
     "surface normal: voxel face or terrain (world, unit; 0: no hit)")
_aov("uv", 2, "mean", lambda batch: batch.voxels is not None, "voxel face UV in [0, 1]")
_aov("material", 1, "first", lambda batch: batch.voxels is not None and (
    len(batch.voxels.materials) > 1 or batch.voxels.texture is not None), "voxel material id (0: no hit)")
_aov("ao", 1, "mean", lambda batch: batch.voxels is not None and (batch.voxels.ao is not None or cone_ao(batch.voxels)),
     "voxel neighbour (or cone-traced: voxels.gi.ao) ambient occlusion (1: open)")
_aov("shadow", 1, "mean", lambda batch: batch.voxels is not None and batch.voxels.shadow is not None and bool(batch.lights),
     "visibility of the first light from the voxel surface (1: lit)")
_aov("water", 1, "mean", lambda batch: batch.voxels is not None and batch.voxels.water is not None,
     "voxel water mask: 1 where the ray met the water plane first (depth is then the water surface)")
_aov("water_floor_distance", 1, "hit_mean", lambda batch: batch.voxels is not None and batch.voxels.water is not None,
     "distance from the camera to the voxel a water-refracted ray reached (world units; 0: none)")
_aov("roughness", 1, "mean", lambda batch: batch.voxels is not None and any_ggx(batch.voxels.materials),
     "voxel material GGX roughness (0: no hit)")
_aov("metallic", 1, "mean", lambda batch: batch.voxels is not None and any_ggx(batch.voxels.materials),
     "voxel material metallic (0: no hit)")
# per-medium labels (torchvol.renderer.labels), computed only when asked for (render(aovs=...), [dataset] aovs)
_aov("optical_thickness", 1, "mean", lambda batch: True,
     "optical thickness τ = ∫σ_t dt along the ray through every volume, to the surface hit (unbounded)", True)
_aov("alpha_volumes", 0, "mean", lambda batch: bool(batch.volumes),
     "each volume's share of alpha, one channel per volume in scene order (V channels)", True)
_aov("instance", 1, "first", lambda batch: True,
     "id of what contributed most: 0 background, 1..V volumes, V + material id (terrain: V + 1, beside M voxel "
     "materials V + M + 1) surfaces", True)
_aov("sun_visibility", 1, "mean", lambda batch: True,
     "transmittance to lights[0] (a sun) from the depth point (median depth, else surface hit); 1: none", True)

# the render's own outputs resolve like AOVs (image, depth and alpha are not AOVs)
RESOLVE = {"alpha": "mean", "depth": "hit_mean", **{k.name: k.resolve for k in AOVS}}


def produced(batch, requested=()) -> list[str]:
    """The AOV names a batch's render computes, in registry order (radiance excluded: an output);
    an `on_request` one only where `requested` names it."""
    return [k.name for k in AOVS if k.name != "radiance" and k.fn(batch)
            and (not k.caps.get("on_request") or k.name in requested)]
