"""How finely to subdivide a mesh: a uniform level from what the stage's cameras see of it.

Each subdivision level halves the edges, so the edge level is the number of halvings that bring
the longest cage edge, as the stage's cameras see it, under `EDGE_PIXELS`. A mesh stops earlier,
from level 1 on, once its control points lie within `FLAT_PIXELS` of the limit surface on screen
(`subdivision.Refinement`): the facets through the limit points are then closer than that to the
limit surface, so flat and gently curved parts do not pay for 1-pixel edges. The projected length
of a segment of length l at distance d is bounded by l f / (d cos^2 theta), f the focal length in pixels
and theta the angle of the image corner (the largest stretch a pinhole gives); d is the distance
to the nearest point the segment can have (its midpoint's distance less half its length), at least
the near clipping distance. The level is the finest any camera of the stage needs (the bake
camera is one of them, and every bake and reference reading the shot at the same image size
refines identically), capped at `MAX_LEVEL` and by `TRIANGLE_BUDGET` triangles per mesh (a
warning says what was given up). A stage without cameras refines `FALLBACK_LEVEL` times.

Instanced meshes take the finest level any placement needs: placements are visited nearest
first (by a bounding-sphere bound of their projected edge size) and the exact edge test stops
once no remaining placement's bound can ask for more.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.scene.types import Camera

EDGE_PIXELS = 1.0
"""Target projected edge length in pixels."""
MAX_LEVEL = 8
"""Most uniform levels any mesh is refined."""
TRIANGLE_BUDGET = 1_000_000
"""Most triangles one subdivided mesh (before instancing) is refined to."""
FLAT_PIXELS = 0.1
"""Refinement stops earlier once every control point is this close (in pixels) to the limit."""
FALLBACK_LEVEL = 2
"""Levels for a stage without perspective cameras."""

_CHUNK_ELEMENTS = 1 << 21  # placements x edges x cameras evaluated at once


@dataclass(frozen=True)
class View:
    """What the level choice needs of a camera.

    Attributes:
        position: (3,) float64 world position of the pinhole.
        focal_pixels: focal length in pixels, divided by cos^2 of the image corner's angle.
        near: near clipping distance (scene units).
    """

    position: np.ndarray
    focal_pixels: float
    near: float


def views_from_cameras(cameras: dict[str, Camera]) -> list[View]:
    """One `View` per camera (at the image size it is rendered at); a camera with no finite, positive
    focal length and aperture projects nothing and sets no dicing rate (rendering from it is refused
    where it is used)."""
    views = []
    for camera in cameras.values():
        lengths = (camera.focal_length, camera.horizontal_aperture)
        if not all(math.isfinite(length) and length > 0 for length in lengths):
            continue
        focal_pixels = camera.focal_length / camera.horizontal_aperture * camera.width
        half_x = camera.horizontal_aperture / 2 + abs(camera.horizontal_aperture_offset)
        half_y = camera.vertical_aperture / 2 + abs(camera.vertical_aperture_offset)
        tan_corner2 = (half_x**2 + half_y**2) / camera.focal_length**2
        views.append(
            View(
                position=np.asarray(camera.world_from_camera[:3, 3], np.float64),
                focal_pixels=focal_pixels * (1.0 + tan_corner2),
                near=max(camera.clipping_range[0], 0.0),
            )
        )
    return views


def _scales(world_from_local: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(I,) largest and smallest singular values of the placements' linear parts."""
    singular = np.linalg.svd(world_from_local[:, :3, :3], compute_uv=False)
    return singular[:, 0], singular[:, -1]


def max_projected_length(
    starts: np.ndarray, ends: np.ndarray, world_from_local: np.ndarray, views: list[View]
) -> float:
    """Largest projected length in pixels of any segment at any placement seen by any view.

    Args:
        starts, ends: (E, 3) local segment end points (cage edges, or limit displacements).
        world_from_local: (I, 4, 4) placements. views: the cameras (at least one).
    """
    if len(starts) == 0 or len(world_from_local) == 0:
        return 0.0
    midpoints = (starts + ends) / 2  # (E, 3)
    half_lengths = np.linalg.norm(ends - starts, axis=-1) / 2
    positions = np.stack([v.position for v in views])  # (C, 3)
    focal = np.array([v.focal_pixels for v in views])
    near = np.maximum(np.array([v.near for v in views]), 1e-12 * max(1.0, float(np.abs(positions).max())))
    s_max, s_min = _scales(world_from_local)
    # Camera positions in each placement's local space: (I, C, 3).
    local_from_world = np.linalg.inv(world_from_local)
    cameras_local = positions @ local_from_world[:, :3, :3].transpose(0, 2, 1) + local_from_world[:, None, :3, 3]

    def pixels(distance_local, length_local, rows):
        # Distances and lengths in local units, broadcast against (..., C); rows: placements.
        scale_max = s_max[rows].reshape((-1,) + (1,) * (distance_local.ndim - 1))
        scale_min = s_min[rows].reshape(scale_max.shape)
        return focal * scale_max * length_local / np.maximum(scale_min * distance_local, near)

    center = midpoints.mean(axis=0)
    radius = float((np.linalg.norm(midpoints - center, axis=-1) + half_lengths).max())
    all_rows = np.arange(len(world_from_local))
    bound_distance = np.maximum(np.linalg.norm(cameras_local - center, axis=-1) - radius, 0.0)  # (I, C)
    bound = pixels(bound_distance, 2 * float(half_lengths.max()), all_rows).max(axis=-1)  # (I,)

    best = 0.0
    order = np.argsort(-bound)
    chunk = max(1, _CHUNK_ELEMENTS // (len(starts) * len(views)))
    for first in range(0, len(order), chunk):
        rows = order[first : first + chunk]
        if bound[rows[0]] <= best:
            break  # no remaining placement can have a longer projected segment
        offsets = midpoints[None, :, None, :] - cameras_local[rows, None, :, :]  # (k, E, C, 3)
        distance = np.maximum(np.linalg.norm(offsets, axis=-1) - half_lengths[None, :, None], 0.0)
        best = max(best, float(pixels(distance, 2 * half_lengths[None, :, None], rows).max()))
    return best


def level_for_pixels(edge_pixels: float, target: float = EDGE_PIXELS) -> int:
    """Halvings that bring `edge_pixels` under `target` (0 when already under), capped at MAX_LEVEL."""
    if not math.isfinite(edge_pixels):
        return MAX_LEVEL
    if edge_pixels <= target:
        return 0
    return min(MAX_LEVEL, math.ceil(math.log2(edge_pixels / target)))
