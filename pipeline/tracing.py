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
    * The Embree queries themselves live in `relight_torch.visibility.embree.EmbreeCaster`; with an
      opacity table, hits in holes of cut-out (and, stochastically, partially opaque) surfaces are
      passed through by every query.
"""

from __future__ import annotations

import copy
import threading
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from pipeline.scene.opacity import scene_opacity
from pipeline.scene.surface import triangle_tangents
from pipeline.scene.types import Geometry, Scene
from relight_torch.visibility.embree import CHUNK_RAYS, EmbreeCaster
from relight_torch.visibility.opacity import OpacityTable


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

    @cached_property
    def tangents(self) -> np.ndarray:
        """(T, 3) float32 per-triangle tangents (`pipeline.scene.surface.triangle_tangents`),
        computed once per soup (every twin of a tracer shares its tables)."""
        return triangle_tangents(self.geometry.positions, self.geometry.uvs)


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
        np.divide(normal, np.sqrt(squared_length)[:, None], out=normal, where=(squared_length > 0)[:, None])
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


class Tracer(EmbreeCaster):
    """Closest-hit and occlusion queries against one `Geometry`, with surface attributes.

    Args:
        geometry: the world-space triangle soup; kept by reference (not copied).
        num_threads: threads tracing chunks of a batch in parallel; default: the CPUs this
            process may use.
        opacity: the soup's non-opaque triangles (`pipeline.scene.opacity.scene_opacity`), whose
            holes every query passes through; None: every triangle is opaque. `for_scene` builds it.
    """

    def __init__(self, geometry: Geometry, num_threads: int | None = None, opacity: OpacityTable | None = None):
        _check_geometry(geometry)
        super().__init__(np.ascontiguousarray(geometry.positions, np.float32), num_threads, opacity=opacity)
        self._surface = SurfaceTables(geometry, _unit_face_normals(self.corners))

    @classmethod
    def for_scene(cls, scene: Scene, num_threads: int | None = None) -> Tracer:
        """The tracer of a scene's soup, with its materials' cut-outs and partial opacity."""
        return cls(scene.geometry, num_threads, scene_opacity(scene))

    @property
    def geometry(self) -> Geometry:
        return self._surface.geometry

    @property
    def tangents(self) -> np.ndarray:
        """(T, 3) float32 per-triangle tangents, computed once per soup (`SurfaceTables.tangents`)."""
        return self._surface.tangents

    def with_threads(self, num_threads: int | None) -> Tracer:
        """This tracer on `num_threads` threads (None: every CPU this process may use); its BVH and
        tables are shared, nothing is rebuilt."""
        twin = copy.copy(self)
        twin.num_threads = EmbreeCaster.thread_count(num_threads)
        return twin

    def intersect(self, origins: np.ndarray, directions: np.ndarray, t_far: np.ndarray | None = None) -> Hits:
        """Closest hit of each ray; its surface attributes are computed when first read.

        Args and shapes as `EmbreeCaster.intersect`.
        """
        ray_hits = super().intersect(origins, directions, t_far)
        return Hits(ray_hits.hit, ray_hits.distance, ray_hits.triangle_id, ray_hits.barycentrics, self._surface)


_SHARED_LOCK = threading.Lock()
_SHARED: list[tuple[Geometry, object, Tracer]] = []  # at most one: (soup, materials, tracer)


def shared_tracer(scene: Scene, num_threads: int | None = None) -> Tracer:
    """The tracer of `scene`'s soup and materials (`Tracer.for_scene`) on `num_threads` threads,
    built once in this process for as long as the same soup is asked for.

    A bake measures one shot at several image sizes (pilots, the measurement window, the reduced
    view of indirect rows) and renders references of it; each is a `dataclasses.replace` of the
    shot's scene, so they all keep its soup and share one BVH (two BVHs of a 33 M-triangle film
    shot held at once had pushed its bake past 19 GB). Only the last soup's tracer is held: a new
    soup releases the old BVH.
    """
    with _SHARED_LOCK:
        if not _SHARED or _SHARED[0][0] is not scene.geometry or _SHARED[0][1] is not scene.materials:
            _SHARED.clear()  # release the old BVH before building the new one
            _SHARED.append((scene.geometry, scene.materials, Tracer.for_scene(scene)))
        tracer = _SHARED[0][2]
    return tracer.with_threads(num_threads)


def _unit_face_normals(corners: np.ndarray) -> np.ndarray:
    """(T + 1, 3) float32 unit normals normalize((p1 - p0) x (p2 - p0)) of (T, 3, 3) triangles,
    then a zero row for misses (`SurfaceTables.face_normals`).

    Computed in float64 so that thin triangles keep an accurate direction; degenerate triangles
    (which Embree never reports as hit) get zero normals.
    """
    unit = np.zeros((corners.shape[0] + 1, 3), np.float32)
    # In chunks: the float64 temporaries stay bounded on big soups.
    for start in range(0, corners.shape[0], CHUNK_RAYS):
        corners64 = corners[start : start + CHUNK_RAYS].astype(np.float64)
        normals = np.cross(corners64[:, 1] - corners64[:, 0], corners64[:, 2] - corners64[:, 0])
        length = np.linalg.norm(normals, axis=-1, keepdims=True)
        unit[start : start + len(corners64)] = np.where(length > 0, normals / np.where(length > 0, length, 1), 0)
    return unit


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
            raise ValueError(f"Geometry.{name} must be {np.dtype(dtype).name} {shape}, got {array.dtype} {array.shape}")
