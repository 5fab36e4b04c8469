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

Each placement of an instanced mesh takes its own level (`projected_lengths` per placement): a
teapot twenty pixels wide is refined far less than the one by the camera, and the placements at
one level share that level's refined surface. A camera sets no rate for what lies outside its
frustum (a bounding sphere per placement against its side and near planes): what no camera sees
is only in shadows and reflections and takes the coarsest level.
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
        world_from_camera: (3, 3) float64 orthonormal rotation (the camera looks down its -Z), or
            None: the view sees every direction.
        tan_half: (2,) tangents of the half-angles of the frustum (x, y; aperture offsets included).
    """

    position: np.ndarray
    focal_pixels: float
    near: float
    world_from_camera: np.ndarray | None = None
    tan_half: tuple[float, float] = (math.inf, math.inf)

    def sees(self, centres: np.ndarray, radii: np.ndarray) -> np.ndarray:
        """(I,) whether spheres (centres (I, 3), radii (I,), world) reach into the view's frustum
        (conservatively: the sphere against each side plane and the near plane)."""
        if self.world_from_camera is None:
            return np.ones(len(centres), bool)
        x, y, z = ((centres - self.position) @ self.world_from_camera).T
        inside = -z + radii >= self.near
        for offset, tangent in ((x, self.tan_half[0]), (y, self.tan_half[1])):
            if math.isfinite(tangent):
                inside &= np.abs(offset) + z * tangent <= radii * math.sqrt(1.0 + tangent * tangent)
        return inside


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
        axes = np.asarray(camera.world_from_camera[:3, :3], np.float64)
        rotation = axes / np.linalg.norm(axes, axis=0)
        tan_half = (half_x / camera.focal_length, half_y / camera.focal_length)
        orthonormal = np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-6) and all(map(math.isfinite, tan_half))
        views.append(
            View(
                position=np.asarray(camera.world_from_camera[:3, 3], np.float64),
                focal_pixels=focal_pixels * (1.0 + tan_corner2),
                near=max(camera.clipping_range[0], 0.0),
                # A sheared camera transform keeps no frustum test (it sees everything).
                world_from_camera=rotation if orthonormal else None,
                tan_half=tan_half if orthonormal else (math.inf, math.inf),
            )
        )
    return views


def projected_lengths(
    starts: np.ndarray, ends: np.ndarray, world_from_local: np.ndarray, views: list[View]
) -> np.ndarray:
    """Largest projected length in pixels of any segment seen by any view, per placement.

    Args:
        starts, ends: (E, 3) local segment end points (cage edges, or limit displacements).
        world_from_local: (I, 4, 4) placements. views: the cameras (at least one).

    Returns:
        (I,) float64 pixels (zeros when there are no segments).
    """
    lengths = np.zeros(len(world_from_local))
    if len(starts) == 0 or len(world_from_local) == 0:
        return lengths
    midpoints = (starts + ends) / 2  # (E, 3)
    half_lengths = np.linalg.norm(ends - starts, axis=-1) / 2
    positions = np.stack([v.position for v in views])  # (C, 3)
    focal = np.array([v.focal_pixels for v in views])
    near = np.maximum(np.array([v.near for v in views]), 1e-12 * max(1.0, float(np.abs(positions).max())))
    singular = np.linalg.svd(world_from_local[:, :3, :3], compute_uv=False)
    s_max, s_min = singular[:, 0], singular[:, -1]
    # Camera positions in each placement's local space: (I, C, 3).
    local_from_world = np.linalg.inv(world_from_local)
    cameras_local = positions @ local_from_world[:, :3, :3].transpose(0, 2, 1) + local_from_world[:, None, :3, 3]
    # Placements outside every view's frustum are not seen (their shadows and reflections take the
    # coarsest level): a bounding sphere of the segments per placement against each frustum.
    centre = midpoints.mean(axis=0)
    radius = float((np.linalg.norm(midpoints - centre, axis=-1) + half_lengths).max())
    centres = world_from_local[:, :3, :3] @ centre + world_from_local[:, :3, 3]
    seen = np.stack([view.sees(centres, radius * s_max) for view in views], axis=-1)  # (I, C)
    chunk = max(1, _CHUNK_ELEMENTS // (len(starts) * len(views)))
    for first in range(0, len(world_from_local), chunk):
        rows = slice(first, first + chunk)
        offsets = midpoints[None, :, None, :] - cameras_local[rows, None, :, :]  # (k, E, C, 3)
        distance = np.maximum(np.linalg.norm(offsets, axis=-1) - half_lengths[None, :, None], 0.0)
        # Distances and lengths in local units: a placement stretches lengths by at most s_max and
        # distances by at least s_min.
        scale_max, scale_min = s_max[rows, None, None], s_min[rows, None, None]
        pixels = focal * scale_max * (2 * half_lengths[None, :, None]) / np.maximum(scale_min * distance, near)
        lengths[rows] = np.where(seen[rows, None, :], pixels, 0.0).max(axis=(1, 2))
    return lengths


def max_projected_length(
    starts: np.ndarray, ends: np.ndarray, world_from_local: np.ndarray, views: list[View]
) -> float:
    """Largest projected length in pixels of any segment at any placement seen by any view
    (`projected_lengths`' maximum)."""
    return float(projected_lengths(starts, ends, world_from_local, views).max(initial=0.0))


def level_for_pixels(edge_pixels: float, target: float = EDGE_PIXELS) -> int:
    """Halvings that bring `edge_pixels` under `target` (0 when already under), capped at MAX_LEVEL."""
    if not math.isfinite(edge_pixels):
        return MAX_LEVEL
    if edge_pixels <= target:
        return 0
    return min(MAX_LEVEL, math.ceil(math.log2(edge_pixels / target)))


def levels_for_pixels(edge_pixels: np.ndarray, target: float = EDGE_PIXELS) -> np.ndarray:
    """(I,) int64 `level_for_pixels` of each of (I,) projected lengths."""
    return np.array([level_for_pixels(float(p), target) for p in edge_pixels], np.int64)
