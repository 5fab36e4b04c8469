"""Filling large holes on demand: a small deep framebuffer of just the surfaces no caching camera saw.

The paper renders a temporary scene of the polygons under the holes; here the new view's own
sub-sample rays through the hole pixels are traced against the shot and their surfaces evaluated
(`pipeline.shading_points`), which is the deep framebuffer baker restricted to those pixels.
Materials are point-sampled (one ray per sub-sample, no texture filtering): patches are small and
meant to be replaced by a re-bake with more cameras when they are not.
"""

from __future__ import annotations

import numpy as np

from pipeline.bake.deep_framebuffer import grid_rays
from pipeline.scene.types import Camera, Scene
from pipeline.shading_points import shading_points
from pipeline.tracing import Tracer, shared_tracer
from relight_torch.gbuffer import GBuffer


def hole_patch(
    scene: Scene,
    camera: Camera,
    supersampling: int,
    pixel_index: np.ndarray,
    tracer: Tracer | None = None,
) -> GBuffer:
    """The G-buffer of `camera`'s sub-samples at `pixel_index` (M,) flat indices of its (H s, W s) image.

    Sub-samples whose rays hit nothing are left out. `tracer`: the scene's (`shared_tracer` when not
    given); a caller patching many frames keeps it.
    """
    tracer = tracer or shared_tracer(scene)
    tangents = tracer.tangents
    origins, directions = grid_rays(camera, supersampling)
    pixel_index = np.asarray(pixel_index, np.int64)
    directions = directions[pixel_index]
    hits = tracer.intersect(origins[pixel_index], directions)
    points = shading_points(scene, tangents, hits, directions)
    centre = camera.world_from_camera[:3, 3]
    forward = -camera.world_from_camera[:3, 2] / np.linalg.norm(camera.world_from_camera[:3, 2])
    return GBuffer.from_numpy(
        image_size=(camera.height * supersampling, camera.width * supersampling),
        pixel_index=pixel_index[hits.hit],
        position=points.position,
        normal=points.normal,
        tangent=points.tangent,
        bitangent=points.bitangent,
        geometric_normal=points.geometric_normal,
        params=points.params,
        material_id=points.material_id,
        object_id=points.object_id,
        depth=((points.position - centre) @ forward).astype(np.float32),
        camera_position=centre,
    )
