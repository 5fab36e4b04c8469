"""Ray tracing against the scene's triangle soup with Embree (through embreex).

`Tracer` wraps one embreex scene built from a `Geometry` and answers two batched queries:
closest hit (`intersect`, returning `Hits` with every surface attribute the bakers need) and
any hit (`occluded`, for shadow rays). Rays are numpy float32 arrays, channels last; nothing loops
in Python over rays or triangles.

Conventions:
    * A ray is origin + t * direction for t in [0, t_far]; directions need not be unit, and
      `Hits.distance` is the ray parameter t (the distance when directions are unit).
    * Barycentrics are Embree's (u, v): the hit point is (1 - u - v) p0 + u p1 + v p2 for the
      triangle's corners p0, p1, p2.
    * The geometric normal is normalize((p1 - p0) x (p2 - p0)): it follows the winding and is NOT
      flipped toward the ray. Shading normals are interpolated from `Geometry.normals`.
    * Ray offsets scale with the scene (`Tracer.epsilon`); there is no fixed world epsilon.

Embreex facts this module relies on (embreex 4.4.0.post1, checked on this machine):
    * `EmbreeScene.run(origins, directions, dists, output=1)` returns a dict with 'u', 'v', 'Ng',
      'tfar', 'primID', 'geomID'; primID is -1 on a miss, where tfar keeps the input t_far. tnear
      is always 0.
    * It WRITES the hit distances back into `dists` for intersect queries, so we pass a copy.
    * `run` releases the GIL while tracing, so chunks traced on a thread pool run in parallel.
    * The only build option exposed is RTC_SCENE_FLAG_ROBUST (`robust=True`): robust traversal,
      no accuracy-reducing optimisations, against rays slipping through the edge shared by two
      triangles (rare misses remain possible: embree/embree#387). Build quality is not exposed.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from embreex import mesh_construction, rtcore_scene

from pipeline.scene.types import Geometry

# Rays per embreex call: bounds the temporary arrays of one chunk (~100 bytes per ray).
CHUNK_RAYS = 1 << 20
# Smallest chunk worth handing to another thread; below it the call overhead dominates.
MIN_THREAD_CHUNK_RAYS = 1 << 14
# Ray offset as a fraction of the scene's bounding-box diagonal.
EPSILON_DIAGONAL_FRACTION = 1e-4
# Ray offset in float32 ulps of the largest absolute coordinate, so that it survives rounding (and
# Embree's own intersection error) when the scene sits far from the origin.
EPSILON_ULPS = 32


@dataclass(frozen=True)
class SurfaceTables:
    """Per-triangle data the hit attributes are gathered from.

    Attributes:
        geometry: the traced soup (T triangles).
        face_normals: (T + 1, 3) float32 unit normals following the winding; row T is zero so that
            triangle id -1 (a miss) gathers a zero normal.
    """

    geometry: Geometry
    face_normals: np.ndarray


@dataclass(frozen=True)
class Hits:
    """Closest hits of a batch of N rays. Misses hold -1 ids, inf distance and zero vectors.

    The first four fields come out of the traversal; the surface attributes below them are
    gathered and interpolated on first access (then cached), so a caller pays only for what it
    reads (see `pipeline.tracing_bench` for the cost of each).

    Attributes:
        hit: (N,) bool, whether the ray hit a triangle before its t_far.
        distance: (N,) float32 ray parameter t of the hit (scene units for unit directions), inf on a miss.
        triangle_id: (N,) int32 index into the Geometry's triangles, -1 on a miss.
        barycentrics: (N, 2) float32 Embree (u, v): weights of corners 1 and 2.
        position: (N, 3) float32 world-space hit point, interpolated from the triangle's corners
            (more precise than origin + t * direction far from the origin).
        geometric_normal: (N, 3) float32 unit world-space face normal, following the winding.
        shading_normal: (N, 3) float32 unit world-space normal interpolated from the corners'
            (the geometric normal where the corners' normals cancel out).
        uv: (N, 2) float32 interpolated 'st' primvar.
        material_id: (N,) int32 index into `Scene.materials`, -1 on a miss.
        object_id: (N,) int32 index into `Scene.objects`, -1 on a miss.
    """

    hit: np.ndarray
    distance: np.ndarray
    triangle_id: np.ndarray
    barycentrics: np.ndarray
    surface: SurfaceTables = field(repr=False, compare=False)

    @property
    def num_rays(self) -> int:
        return int(self.hit.shape[0])

    @cached_property
    def position(self) -> np.ndarray:
        return self._interpolate(self.surface.geometry.positions)

    @cached_property
    def geometric_normal(self) -> np.ndarray:
        return np.take(self.surface.face_normals, self.triangle_id, axis=0)

    @cached_property
    def shading_normal(self) -> np.ndarray:
        normal = self._interpolate(self.surface.geometry.normals)
        squared_length = np.einsum("nk,nk->n", normal, normal)
        np.divide(normal, np.sqrt(squared_length)[:, None], out=normal,
                  where=(squared_length > 0)[:, None])
        degenerate = self.hit & (squared_length == 0)
        if degenerate.any():
            normal[degenerate] = self.surface.face_normals[self.triangle_id[degenerate]]
        return normal

    @cached_property
    def uv(self) -> np.ndarray:
        return self._interpolate(self.surface.geometry.uvs)

    @cached_property
    def material_id(self) -> np.ndarray:
        return self._gather_id(self.surface.geometry.material_ids)

    @cached_property
    def object_id(self) -> np.ndarray:
        return self._gather_id(self.surface.geometry.object_ids)

    @cached_property
    def _safe_triangle_id(self) -> np.ndarray:
        """(N,) triangle ids with misses sent to triangle 0 (their results are zeroed after)."""
        return np.maximum(self.triangle_id, 0)

    def _gather_id(self, per_triangle: np.ndarray) -> np.ndarray:
        """(N,) int32 per-triangle ids at the hits, -1 on misses."""
        if per_triangle.shape[0] == 0:
            return np.full(self.num_rays, -1, np.int32)
        return np.where(self.hit, np.take(per_triangle, self._safe_triangle_id), -1).astype(np.int32)

    def _interpolate(self, corner_values: np.ndarray) -> np.ndarray:
        """Barycentric interpolation of (T, 3, C) per-corner values: (N, C) float32, zero on misses.

        Chunked so that the (chunk, 3, C) gathered corners stay bounded.
        """
        values = np.zeros((self.num_rays, corner_values.shape[-1]), np.float32)
        if corner_values.shape[0] == 0:
            return values
        for start in range(0, self.num_rays, CHUNK_RAYS):
            chunk = slice(start, start + CHUNK_RAYS)
            u, v = self.barycentrics[chunk, 0], self.barycentrics[chunk, 1]
            weights = np.stack([1 - u - v, u, v], axis=-1)
            corners = np.take(corner_values, self._safe_triangle_id[chunk], axis=0)
            # einsum beats broadcasting weights[:, :, None] here: numpy's inner loops over the
            # 3-long last axis are slow.
            np.einsum("nc,nck->nk", weights, corners, out=values[chunk])
        values[~self.hit] = 0
        return values


class Tracer:
    """Closest-hit and occlusion queries against one `Geometry`.

    Args:
        geometry: the world-space triangle soup; kept by reference (not copied).
        num_threads: threads tracing chunks of a batch in parallel; default: the CPUs this
            process may use.

    Attributes:
        epsilon: ray offset in scene units: the larger of 1e-4 x the bounding-box diagonal and 32
            float32 ulps of the largest coordinate. Use it through `offset_origins`.
    """

    def __init__(self, geometry: Geometry, num_threads: int | None = None):
        _check_geometry(geometry)
        self.num_threads = num_threads or len(os.sched_getaffinity(0))
        corners = np.ascontiguousarray(geometry.positions, np.float32)
        self._surface = SurfaceTables(geometry, _unit_face_normals(corners))
        self._scene = rtcore_scene.EmbreeScene(robust=True)
        if geometry.num_triangles:
            mesh_construction.TriangleMesh(self._scene, corners)
        # An empty query commits (builds) the scene now rather than on the first real batch.
        self._scene.run(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32))
        self.epsilon = _scene_epsilon(corners)

    @property
    def geometry(self) -> Geometry:
        return self._surface.geometry

    def intersect(self, origins: np.ndarray, directions: np.ndarray,
                  t_far: np.ndarray | None = None) -> Hits:
        """Closest hit of each ray; its surface attributes are computed when first read.

        Args:
            origins: (N, 3) float32 world-space ray origins.
            directions: (N, 3) float32 world-space ray directions (need not be unit).
            t_far: (N,) float32 largest ray parameter to accept, or None for unbounded.

        Returns:
            `Hits` of N rays.
        """
        num_rays = _check_rays(origins, directions, t_far)
        distance = np.empty(num_rays, np.float32)
        triangle_id = np.empty(num_rays, np.int32)
        barycentrics = np.empty((num_rays, 2), np.float32)

        def trace(chunk: slice) -> None:
            dists = (np.full(chunk.stop - chunk.start, np.inf, np.float32) if t_far is None
                     else np.array(t_far[chunk], np.float32))
            raw = self._scene.run(origins[chunk], directions[chunk], dists=dists, output=1)
            hit = raw["primID"] >= 0
            triangle_id[chunk] = raw["primID"]
            distance[chunk] = np.where(hit, raw["tfar"], np.inf)
            barycentrics[chunk, 0] = np.where(hit, raw["u"], 0)
            barycentrics[chunk, 1] = np.where(hit, raw["v"], 0)

        self._map_chunks(trace, num_rays)
        return Hits(triangle_id >= 0, distance, triangle_id, barycentrics, self._surface)

    def occluded(self, origins: np.ndarray, directions: np.ndarray, t_far: np.ndarray) -> np.ndarray:
        """Whether anything lies on each ray for t in [0, t_far] (Embree's any-hit query).

        Args:
            origins: (N, 3) float32 world-space ray origins (offset them with `offset_origins`).
            directions: (N, 3) float32 world-space ray directions.
            t_far: (N,) float32 ray parameter of the light or point to reach; shorten it by
                `epsilon` (in distance) so that the receiving surface does not occlude itself.

        Returns:
            (N,) bool, True where the ray is blocked.
        """
        num_rays = _check_rays(origins, directions, t_far, t_far_required=True)
        blocked = np.zeros(num_rays, bool)

        def trace(chunk: slice) -> None:
            geometry_ids = self._scene.run(origins[chunk], directions[chunk],
                                           dists=np.array(t_far[chunk], np.float32), query="OCCLUDED")
            blocked[chunk] = geometry_ids != -1

        self._map_chunks(trace, num_rays)
        return blocked

    def offset_origins(self, points: np.ndarray, normals: np.ndarray,
                       directions: np.ndarray) -> np.ndarray:
        """Push surface points off their surface, to the side rays will leave towards.

        Args:
            points: (N, 3) float32 world-space points on the surface.
            normals: (N, 3) float32 unit geometric normals at the points (either orientation).
            directions: (N, 3) float32 directions of the rays that will leave the points.

        Returns:
            (N, 3) float32 points + epsilon * normal, the normal flipped to the directions' side
            (kept as is where the direction is tangent).
        """
        side = np.where(np.einsum("nk,nk->n", normals, directions) < 0, -1.0, 1.0).astype(np.float32)
        return (points + (np.float32(self.epsilon) * side)[:, None] * normals).astype(np.float32)

    def _map_chunks(self, trace, num_rays: int) -> None:
        """Call `trace(chunk_slice)` over the batch, on a thread pool when it pays."""
        num_chunks = max(-(-num_rays // CHUNK_RAYS),
                         min(self.num_threads, num_rays // MIN_THREAD_CHUNK_RAYS), 1)
        bounds = np.linspace(0, num_rays, num_chunks + 1).astype(np.int64)
        chunks = [slice(int(start), int(stop)) for start, stop in zip(bounds[:-1], bounds[1:])]
        if len(chunks) == 1 or self.num_threads == 1:
            for chunk in chunks:
                trace(chunk)
            return
        with ThreadPoolExecutor(min(self.num_threads, len(chunks))) as pool:
            # list() re-raises the first exception of a chunk.
            list(pool.map(trace, chunks))


def _unit_face_normals(corners: np.ndarray) -> np.ndarray:
    """(T + 1, 3) float32 unit normals normalize((p1 - p0) x (p2 - p0)) of (T, 3, 3) triangles,
    then a zero row for misses (`SurfaceTables.face_normals`).

    Computed in float64 so that thin triangles keep an accurate direction; degenerate triangles
    (which Embree never reports as hit) get zero normals.
    """
    corners64 = corners.astype(np.float64)
    normals = np.cross(corners64[:, 1] - corners64[:, 0], corners64[:, 2] - corners64[:, 0])
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    unit = np.where(length > 0, normals / np.where(length > 0, length, 1), 0)
    return np.concatenate([unit, np.zeros((1, 3))]).astype(np.float32)


def _scene_epsilon(corners: np.ndarray) -> float:
    """Ray offset for a (T, 3, 3) soup: see `Tracer.epsilon`. 0 for an empty soup."""
    if corners.shape[0] == 0:
        return 0.0
    points = corners.reshape(-1, 3).astype(np.float64)
    diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    magnitude = float(np.abs(points).max())
    return max(EPSILON_DIAGONAL_FRACTION * diagonal,
               EPSILON_ULPS * float(np.spacing(np.float32(magnitude))))


def _check_geometry(geometry: Geometry) -> None:
    """Raise ValueError unless the soup's arrays have the documented shapes and dtypes."""
    num_triangles = geometry.num_triangles
    expected = {
        "positions": ((num_triangles, 3, 3), np.float32),
        "normals": ((num_triangles, 3, 3), np.float32),
        "uvs": ((num_triangles, 3, 2), np.float32),
        "material_ids": ((num_triangles,), np.int32),
        "object_ids": ((num_triangles,), np.int32),
    }
    for name, (shape, dtype) in expected.items():
        array = getattr(geometry, name)
        if array.shape != shape or array.dtype != dtype:
            raise ValueError(f"Geometry.{name} must be {np.dtype(dtype).name} {shape}, "
                             f"got {array.dtype} {array.shape}")


def _check_rays(origins: np.ndarray, directions: np.ndarray, t_far: np.ndarray | None,
                t_far_required: bool = False) -> int:
    """Raise ValueError unless origins, directions are float32 (N, 3) and t_far float32 (N,).

    Returns:
        N, the number of rays.
    """
    for name, array in (("origins", origins), ("directions", directions)):
        if array.dtype != np.float32 or array.ndim != 2 or array.shape[1] != 3:
            raise ValueError(f"{name} must be float32 (N, 3), got {array.dtype} {array.shape}")
    num_rays = origins.shape[0]
    if directions.shape[0] != num_rays:
        raise ValueError(f"directions must be ({num_rays}, 3) like origins, got {directions.shape}")
    if t_far is None:
        if t_far_required:
            raise ValueError("t_far is required: (N,) float32")
    elif t_far.dtype != np.float32 or t_far.shape != (num_rays,):
        raise ValueError(f"t_far must be float32 ({num_rays},), got {t_far.dtype} {t_far.shape}")
    return num_rays
