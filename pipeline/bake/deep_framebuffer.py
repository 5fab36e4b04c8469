"""The deep framebuffer (Gershbein & Hanrahan 2000): what the camera sees, ready to relight.

Per sub-sample of every pixel: world position, shading frame (normal map applied), geometric
normal, the UsdPreviewSurface parameters with textures evaluated, material and object ids, depth
and coverage. With supersampling s, each pixel holds s x s sub-samples on a regular grid; they are
shaded separately by the relighter and box-filtered after shading.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.scene.camera import camera_rays
from pipeline.scene.surface import triangle_tangents
from pipeline.scene.types import Camera, Scene
from pipeline.shading_points import shading_points
from pipeline.tracing import Tracer
from relight_torch.gbuffer import GBuffer


@dataclass(frozen=True)
class DeepFramebuffer:
    """A baked deep framebuffer.

    Attributes:
        gbuffer: the covered sub-samples (N of them) as a relight_torch GBuffer (CPU tensors).
        camera: the camera it was baked from.
        supersampling: s; the sub-sample image is (H s, W s).
    """

    gbuffer: GBuffer
    camera: Camera
    supersampling: int


def sub_sample_offsets(supersampling: int) -> list[tuple[int, int, np.ndarray]]:
    """The regular s x s grid inside a pixel: (row, col, offset (2,) in [0, 1)) per sub-sample."""
    grid = (np.arange(supersampling, dtype=np.float32) + 0.5) / supersampling
    return [(i, j, np.array([grid[j], grid[i]], np.float32)) for i in range(supersampling) for j in range(supersampling)]


def bake_deep_framebuffer(scene: Scene, camera: Camera, supersampling: int = 1,
                          tracer: Tracer | None = None) -> DeepFramebuffer:
    """Trace the camera's sub-sample rays and record the visible surfaces.

    Args:
        scene: the shot.
        camera: the camera (its width and height set the resolution).
        supersampling: s >= 1 sub-samples per pixel side.
        tracer: reuse a built tracer (the BVH is built otherwise).
    """
    if supersampling < 1:
        raise ValueError(f"supersampling must be >= 1, got {supersampling}")
    tracer = tracer or Tracer(scene.geometry)
    height, width, s = camera.height, camera.width, supersampling
    origins = np.empty((height * s, width * s, 3), np.float32)
    directions = np.empty_like(origins)
    for i, j, offset in sub_sample_offsets(s):
        o, d = camera_rays(camera, np.broadcast_to(offset, (height, width, 2)).copy())
        origins[i::s, j::s], directions[i::s, j::s] = o, d
    origins, directions = origins.reshape(-1, 3), directions.reshape(-1, 3)
    hits = tracer.intersect(origins, directions)
    tangents = triangle_tangents(scene.geometry.positions, scene.geometry.uvs)
    points = shading_points(scene, tangents, hits, directions)
    camera_position = camera.world_from_camera[:3, 3]
    forward = -camera.world_from_camera[:3, 2] / np.linalg.norm(camera.world_from_camera[:3, 2])
    depth = (points.position - camera_position) @ forward
    gbuffer = GBuffer.from_numpy(
        image_size=(height * s, width * s),
        pixel_index=np.flatnonzero(hits.hit),
        position=points.position, normal=points.normal, tangent=points.tangent,
        bitangent=points.bitangent, geometric_normal=points.geometric_normal,
        params=points.params, material_id=points.material_id, object_id=points.object_id,
        depth=depth.astype(np.float32), camera_position=camera_position,
    )
    return DeepFramebuffer(gbuffer=gbuffer, camera=camera, supersampling=s)
