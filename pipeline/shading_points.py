"""Ray hits turned into shading points: the material evaluated, the shading frame built.

One function shared by the reference renderer and the bakers, so a pixel of the deep framebuffer
and a path vertex of the reference see exactly the same surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.scene.surface import evaluate_materials, shading_frame
from pipeline.scene.types import Scene
from pipeline.tracing import Hits
from relight_torch.brdf.preview_surface import PreviewSurfaceParams


@dataclass(frozen=True)
class ShadingPoints:
    """N surface points ready to shade, world space, float32.

    Attributes:
        position: (N, 3) hit position.
        geometric_normal: (N, 3) unit, flipped to face the incoming ray.
        tangent, bitangent, normal: (N, 3) unit shading frame (normal map applied), normal facing
            the incoming ray's side.
        wo_world: (N, 3) unit direction towards the viewer (minus the ray direction).
        params: per-point UsdPreviewSurface parameters (torch, CPU, float32).
        object_id, material_id: (N,) int32.
    """

    position: np.ndarray
    geometric_normal: np.ndarray
    tangent: np.ndarray
    bitangent: np.ndarray
    normal: np.ndarray
    wo_world: np.ndarray
    params: PreviewSurfaceParams
    object_id: np.ndarray
    material_id: np.ndarray


def shading_points(scene: Scene, tangents: np.ndarray, hits: Hits, ray_directions: np.ndarray) -> ShadingPoints:
    """Evaluate materials and shading frames at the rays' hits (only hits are kept).

    Args:
        scene: the scene the hits are in.
        tangents: (T, 3) per-triangle tangents (`pipeline.scene.surface.triangle_tangents`).
        hits: closest hits of N rays; rays that missed are dropped.
        ray_directions: (N, 3) unit directions of those rays.
    """
    hit = hits.hit
    direction = ray_directions[hit]
    wo = -direction
    geometric = hits.geometric_normal[hit]
    # Two-sided shading: both normals face the side the ray came from.
    flip = np.sum(geometric * wo, axis=-1) < 0.0
    geometric = np.where(flip[:, None], -geometric, geometric)
    smooth = np.where(flip[:, None], -hits.shading_normal[hit], hits.shading_normal[hit])
    material_id = hits.material_id[hit]
    values = evaluate_materials(scene.materials, material_id, hits.uv[hit])
    normal_tangent = values.pop("normal_tangent")
    t, b, n = shading_frame(smooth, tangents[hits.triangle_id[hit]], normal_tangent)
    return ShadingPoints(
        position=hits.position[hit],
        geometric_normal=geometric.astype(np.float32),
        tangent=t,
        bitangent=b,
        normal=n,
        wo_world=wo.astype(np.float32),
        params=PreviewSurfaceParams.from_numpy(values),
        object_id=hits.object_id[hit],
        material_id=material_id,
    )
