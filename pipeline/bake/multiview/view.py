"""A new view's visible points: Embree primary rays against the cache's occluder triangles.

Rays on the same s x s sub-sample grid as the deep framebuffer baker (`grid_rays`); the hit point
is interpolated from the triangle's corners, the geometric normal (the winding's) is turned to
face the camera, the smooth shading normal is interpolated from the corners' normals (turned
likewise), and the object comes from the cache's per-triangle object ids.
"""

from __future__ import annotations

import numpy as np
import torch

from pipeline.bake.deep_framebuffer import grid_rays
from pipeline.scene.types import Camera
from relight_torch.multiview.correspondence import ViewPoints
from relight_torch.visibility.embree import EmbreeCaster


def view_points(
    caster: EmbreeCaster,
    occluder_objects: np.ndarray,
    camera: Camera,
    supersampling: int = 1,
    corner_normals: np.ndarray | None = None,
) -> ViewPoints:
    """The surfaces `camera` sees, one per covered sub-sample of its (H s, W s) image (CPU tensors).

    Args:
        caster: Embree over the occluder triangles (`MultiviewRelighter.caster`).
        occluder_objects: (T,) object id of each triangle.
        camera: the new camera (its width and height set the image).
        supersampling: s.
        corner_normals: (T, 3, 3) shading normals of the triangles' corners, or None (no
            `ViewPoints.shading_normal` then).
    """
    origins, directions = grid_rays(camera, supersampling)
    hits = caster.intersect(origins, directions)
    index = np.flatnonzero(hits.hit)
    triangle = hits.triangle_id[index]
    corners = caster.corners[triangle].astype(np.float64)
    u, v = hits.barycentrics[index, 0:1], hits.barycentrics[index, 1:2]
    position = (1.0 - u - v) * corners[:, 0] + u * corners[:, 1] + v * corners[:, 2]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    side = np.where(np.einsum("nk,nk->n", normal, directions[index]) > 0, -1.0, 1.0)[:, None]
    normal *= side
    shading = None
    if corner_normals is not None:
        smooth = np.einsum(
            "nc,nck->nk",
            np.concatenate([1.0 - u - v, u, v], -1),
            np.asarray(corner_normals)[triangle].astype(np.float64),
        )
        length = np.linalg.norm(smooth, axis=-1, keepdims=True)
        smooth = np.where(length > 1e-12, smooth / np.maximum(length, 1e-12), normal * side) * side
        shading = torch.from_numpy(smooth.astype(np.float32))
    centre = camera.world_from_camera[:3, 3]
    forward = -camera.world_from_camera[:3, 2] / np.linalg.norm(camera.world_from_camera[:3, 2])
    return ViewPoints(
        image_size=(camera.height * supersampling, camera.width * supersampling),
        pixel_index=torch.from_numpy(index.astype(np.int64)),
        position=torch.from_numpy(position.astype(np.float32)),
        geometric_normal=torch.from_numpy(normal.astype(np.float32)),
        object_id=torch.from_numpy(np.asarray(occluder_objects)[triangle].astype(np.int64)),
        depth=torch.from_numpy(((position - centre) @ forward).astype(np.float32)),
        camera_position=torch.from_numpy(centre.astype(np.float32)),
        shading_normal=shading,
    )
