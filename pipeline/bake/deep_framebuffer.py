"""The deep framebuffer (Gershbein & Hanrahan 2000): what the camera sees, ready to relight.

Per sub-sample of every pixel: world position, shading frame (normal map applied), geometric
normal, the UsdPreviewSurface parameters with textures evaluated, material and object ids, depth
and coverage. With supersampling s, each pixel holds s x s sub-samples on a regular grid; they are
shaded separately by the relighter and box-filtered after shading.

Opacity: camera rays pass through cut-out holes to the surface behind (the tracer's opacity
lookup); a partially opaque surface is present in a fraction of the sub-samples equal to its
opacity (stochastic presence, the same decision the reference makes per path), so a pixel's
coverage of sub-samples composites it over what lies behind. Chosen over a second composited
layer for one code path and no new cache channels; its error falls with the sub-sample count: the
leaves scene with its leaves and lattice at a constant opacity 0.5 relit against the reference
(96 x 72) reads 33.9 dB at supersampling 2 and 38.9 dB at 4 (cut-outs: 38.6 dB at 2). A second
layer (front surface, alpha, surface behind) would be exact at any supersampling: not built.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from pipeline.scene.camera import camera_rays
from pipeline.scene.surface import tangent_about
from pipeline.scene.types import Camera, Scene
from pipeline.shading_points import ShadingPoints, shading_points
from pipeline.tracing import Tracer, shared_tracer
from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.gbuffer import GBuffer


@dataclass(frozen=True)
class DeepFramebuffer:
    """A baked deep framebuffer.

    Attributes:
        gbuffer: the covered sub-samples (N of them) as a relight_torch GBuffer (CPU tensors).
        camera: the camera it was baked from.
        supersampling: s; the sub-sample image is (H s, W s).
        num_back_facing: covered sub-samples whose centre ray hit the back of a single-sided
            surface (most of them do when the camera is inside geometry).
    """

    gbuffer: GBuffer
    camera: Camera
    supersampling: int
    num_back_facing: int = 0


def grid_rays(camera: Camera, n: int, rows: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Rays through an n x n regular grid inside every pixel of pixel rows `rows` = [first, last)
    (None: all), as (h n W n, 3) origins and directions in image order of the (h n, W n)
    sub-sample image of those h rows."""
    first, last = rows or (0, camera.height)
    height, width = last - first, camera.width
    origins = np.empty((height * n, width * n, 3), np.float32)
    directions = np.empty_like(origins)
    grid = (np.arange(n, dtype=np.float32) + 0.5) / n
    for i in range(n):
        for j in range(n):
            offset = np.broadcast_to(np.array([grid[j], grid[i]], np.float32), (height, width, 2)).copy()
            origins[i::n, j::n], directions[i::n, j::n] = camera_rays(camera, offset, (first, last))
    return origins.reshape(-1, 3), directions.reshape(-1, 3)


def bake_deep_framebuffer(
    scene: Scene,
    camera: Camera,
    supersampling: int = 1,
    texture_samples: int = 2,
    tracer: Tracer | None = None,
    rows: tuple[int, int] | None = None,
) -> DeepFramebuffer:
    """Trace the camera's sub-sample rays and record the visible surfaces.

    Textures and normal maps are filtered over each sub-sample's footprint so that the relit pixel
    converges to the reference's pixel average: the material parameters and the normal-mapped normal
    of a sub-sample are averaged over a grid of rays inside it that hit the same object as its
    centre ray, 2 x 2 first and t x t where those differ or a texture is minified
    (`_filter_materials`). Geometry (position, geometric normal, depth, ids) is the centre ray's.

    Args:
        scene: the shot.
        camera: the camera (its width and height set the resolution).
        supersampling: s >= 1 sub-samples per pixel side.
        texture_samples: t >= 1 material samples per sub-sample side where materials vary
            (1 = point-sampled textures).
        tracer: the tracer to use (default: the scene's `shared_tracer`).
        rows: bake only the pixel rows [first, last) (a chunk of a bake; the sub-samples keep
            their indices in the whole (H s, W s) image); None: every row.
    """
    if supersampling < 1 or texture_samples < 1:
        raise ValueError(f"supersampling and texture_samples must be >= 1, got {supersampling}, {texture_samples}")
    tracer = tracer or shared_tracer(scene)
    first, last = rows or (0, camera.height)
    if not 0 <= first < last <= camera.height:
        raise ValueError(f"rows must lie in [0, {camera.height}), got [{first}, {last})")
    height, width, s = camera.height, camera.width, supersampling
    tangents = tracer.tangents
    origins, directions = grid_rays(camera, s, (first, last))
    hits = tracer.intersect(origins, directions)
    points = shading_points(scene, tangents, hits, directions)
    band_index = np.flatnonzero(hits.hit)
    double_sided = np.array([obj.double_sided for obj in scene.objects], bool)
    single_sided = ~double_sided[scene.geometry.object_ids[hits.triangle_id[band_index]]]
    facing_away = np.einsum("nk,nk->n", hits.geometric_normal[band_index], directions[band_index]) > 0
    num_back_facing = int(np.count_nonzero(single_sided & facing_away))
    params, normal, tangent, bitangent = points.params, points.normal, points.tangent, points.bitangent
    if texture_samples > 1:
        params, normal, tangent, bitangent = _filter_materials(
            scene, tracer, tangents, camera, s, texture_samples, (first, last), band_index, points
        )
    pixel_index = band_index + first * s * width * s
    camera_position = camera.world_from_camera[:3, 3]
    forward = -camera.world_from_camera[:3, 2] / np.linalg.norm(camera.world_from_camera[:3, 2])
    depth = (points.position - camera_position) @ forward
    gbuffer = GBuffer.from_numpy(
        image_size=(height * s, width * s),
        pixel_index=pixel_index,
        position=points.position,
        normal=normal,
        tangent=tangent,
        bitangent=bitangent,
        geometric_normal=points.geometric_normal,
        params=params,
        material_id=points.material_id,
        object_id=points.object_id,
        depth=depth.astype(np.float32),
        camera_position=camera_position,
    )
    return DeepFramebuffer(gbuffer=gbuffer, camera=camera, supersampling=s, num_back_facing=num_back_facing)


def _fold_normal_spread(params: dict[str, np.ndarray], length: np.ndarray) -> None:
    """Widen the specular lobes by the spread of averaged normals (mean length `length` (N,) in (0, 1]).

    Toksvig's method: the normals' spread, as a von Mises-Fisher lobe of concentration
    kappa = (3 |n| - |n|^3) / (1 - |n|^2), adds 2 / kappa to the GGX alpha^2 (alpha = roughness^2, as
    UsdPreviewSurface squares it). The diffuse part needs no widening (`_average_samples`).
    """
    spread = 1.0 - length * length
    inverse_kappa = np.where(spread > 1e-6, spread / np.maximum(3.0 * length - length**3, 1e-6), 0.0)
    # Only where the lobe exists, so that a material without it keeps a constant (elided) channel.
    has_lobe = {
        "roughness": ~(params["use_specular_workflow"] & np.all(params["specular_color"] == 0, axis=-1)),
        "clearcoat_roughness": params["clearcoat"] > 0,
    }
    for name, lobe in has_lobe.items():
        alpha = np.square(params[name].astype(np.float64))
        widened = np.power(alpha * alpha + 2.0 * inverse_kappa, 0.25).astype(np.float32)
        params[name] = np.where(lobe, widened, params[name])


PROBE_SAMPLES = 2
"""Material samples per sub-sample side of the first pass; sub-samples whose samples differ get
the requested count (`bake_deep_framebuffer`'s texture_samples) in a second pass."""

VARIATION = 0.01
"""A sub-sample is refined where a material parameter's standard deviation over its probe samples
exceeds this, or the spread 1 - |mean normal| of their normals exceeds a tenth of it."""


def _filter_materials(
    scene: Scene,
    tracer: Tracer,
    tangents: np.ndarray,
    camera: Camera,
    s: int,
    t: int,
    rows: tuple[int, int],
    pixel_index: np.ndarray,
    centre: ShadingPoints,
):
    """Average material parameters and shading normals of t x t rays per covered sub-sample,
    adaptively: `PROBE_SAMPLES` per side first, t only where those differ (textured or normal-mapped
    surfaces; a constant material on a smooth surface is already converged).

    Args:
        rows: the pixel rows [first, last) baked; pixel_index: (N,) the covered sub-samples'
            indices in the (h s, W s) sub-sample image of those h rows.

    Returns (params, normal, tangent, bitangent) for the N covered sub-samples, the frame
    re-orthonormalised around the averaged normal.
    """
    probe = min(t, PROBE_SAMPLES)
    filtered, normal, spread_length, varies = _average_samples(
        scene, tracer, tangents, camera, s, probe, rows, pixel_index, centre, None
    )
    if t > probe and varies.any():
        fine = _average_samples(scene, tracer, tangents, camera, s, t, rows, pixel_index, centre, varies)
        filtered = {
            name: np.where(varies.reshape((-1,) + (1,) * (value.ndim - 1)), fine[0][name], value)
            for name, value in filtered.items()
        }
        normal = np.where(varies[:, None], fine[1], normal)
        spread_length = np.where(varies, fine[2], spread_length)
    _fold_normal_spread(filtered, spread_length)
    # The averaged normal may lie along the centre's tangent (samples on both sides of an edge).
    tangent = tangent_about(normal, centre.tangent)
    bitangent = np.cross(normal, tangent).astype(np.float32)
    return PreviewSurfaceParams.from_numpy(filtered), normal, tangent.astype(np.float32), bitangent


def _average_samples(
    scene: Scene,
    tracer: Tracer,
    tangents: np.ndarray,
    camera: Camera,
    s: int,
    t: int,
    rows: tuple[int, int],
    pixel_index: np.ndarray,
    centre: ShadingPoints,
    selected: np.ndarray | None,
):
    """Trace t x t rays per covered sub-sample (only the `selected` (N,) ones where given) and
    average what the rays that see the centre's object hit.

    Returns:
        params: name -> (N, ...) averaged UsdPreviewSurface parameters (bool ones the centre's);
        normal: (N, 3) unit mean shading normal of the samples facing the viewer;
        spread_length: (N,) |mean normal| of those samples, in (0, 1], for `_fold_normal_spread`;
        varies: (N,) bool, whether the samples differ (see `VARIATION`).
        Sub-samples without samples keep the centre's values.
    """
    height, width = rows[1] - rows[0], camera.width
    slot = np.full(height * s * width * s, -1, np.int64)
    slot[pixel_index] = np.arange(pixel_index.size)
    origins, directions = grid_rays(camera, s * t, rows)
    ray_row, ray_col = np.divmod(np.arange(origins.shape[0]), width * s * t)
    ray_owner = slot[(ray_row // t) * (width * s) + ray_col // t]
    traced = np.flatnonzero(ray_owner >= 0 if selected is None else (ray_owner >= 0) & selected[ray_owner])
    hits = tracer.intersect(origins[traced], directions[traced])
    fine = shading_points(scene, tangents, hits, directions[traced])
    owner = ray_owner[traced[hits.hit]]
    same = fine.object_id == centre.object_id[owner]
    fine_kept = np.flatnonzero(same)
    owner = owner[same]
    counts = np.maximum(np.bincount(owner, minlength=pixel_index.size), 1).astype(np.float64)
    has = np.bincount(owner, minlength=pixel_index.size) > 0

    def average(fine_values: np.ndarray, centre_values: np.ndarray) -> np.ndarray:
        flat = fine_values[fine_kept].reshape(owner.size, int(np.prod(centre_values.shape[1:]))).astype(np.float64)
        sums = np.stack([np.bincount(owner, flat[:, c], pixel_index.size) for c in range(flat.shape[1])], -1)
        mean = (sums / counts[:, None]).reshape(centre_values.shape).astype(np.float32)
        return np.where(has.reshape((-1,) + (1,) * (centre_values.ndim - 1)), mean, centre_values)

    fields = {f.name: getattr(centre.params, f.name).numpy() for f in dataclasses.fields(centre.params)}
    fine_fields = {name: getattr(fine.params, name).numpy() for name in fields}
    filtered, varies = {}, np.zeros(pixel_index.size, bool)
    for name, values in fields.items():
        if values.dtype == bool:
            filtered[name] = values
            continue
        filtered[name] = average(fine_fields[name], values)
        second = average(np.square(fine_fields[name].astype(np.float64)), np.square(values.astype(np.float64)))
        # Channels spelt out: with no covered sample (a chunk of sky rows) -1 is ambiguous.
        variance = (second - np.square(filtered[name].astype(np.float64))).reshape(
            pixel_index.size, int(np.prod(values.shape[1:]))
        )
        varies |= np.any(variance > VARIATION**2, axis=-1)
    # The shading model is zero where the shading normal faces away from the viewer (the view is
    # fixed here), so such samples are black: they add nothing to the sums below.
    visible = (np.einsum("nk,nk->n", fine.normal, fine.wo_world) > 0).astype(np.float32)
    normal = average(fine.normal * visible[:, None], centre.normal)
    length = np.linalg.norm(normal, axis=-1, keepdims=True)
    # Every sample faces away (black in the reference): keep the centre's frame; the colour is zero below.
    normal = np.where(length > 1e-6, normal / np.maximum(length, 1e-6), centre.normal).astype(np.float32)
    # Lambertian light is linear in the normal: sum_i a_i (n_i . l) = (sum_i a_i n_i) . l, kept as the
    # colour on the mean normal (exact away from the light's horizon), so colour and normal stay correlated.
    projection = np.zeros(visible.shape, np.float32)
    projection[fine_kept] = np.einsum("nk,nk->n", fine.normal[fine_kept], normal[owner]) * visible[fine_kept]
    filtered["diffuse_color"] = average(fine_fields["diffuse_color"] * projection[:, None], fields["diffuse_color"])
    visible_mean = average(visible[:, None], np.ones((pixel_index.size, 1), np.float32))[:, 0]
    spread_length = np.clip(length[:, 0] / np.maximum(visible_mean, 1e-6), 1e-6, 1.0)
    varies |= (1.0 - spread_length) > 0.1 * VARIATION
    # A probe can miss what its footprint holds (a mortar line between bricks): refine wherever the
    # probe samples span more than half a texel of a texture of the material.
    uv = hits.uv[hits.hit][fine_kept].astype(np.float64)
    low = np.full((pixel_index.size, 2), np.inf)
    high = np.full((pixel_index.size, 2), -np.inf)
    np.minimum.at(low, owner, uv)
    np.maximum.at(high, owner, uv)
    span = np.where(has[:, None], high - low, 0.0).max(axis=-1)
    varies |= span * texel_density(scene)[centre.material_id] > 0.5
    return filtered, normal, spread_length, varies & has


def texel_density(scene: Scene) -> np.ndarray:
    """(M,) texels per unit of texture coordinate of each material's densest texture (0: untextured)."""
    density = np.zeros(len(scene.materials))
    for index, material in enumerate(scene.materials):
        for field in dataclasses.fields(material):
            texture = getattr(getattr(material, field.name), "texture", None)
            if texture is not None:
                stretch = np.linalg.norm(texture.st_from_uv[:2, :2], 2)  # largest singular value
                density[index] = max(density[index], max(texture.pixels.shape[:2]) * stretch)
    return density
