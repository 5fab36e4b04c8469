"""Embree ray queries over a world-space triangle soup (through embreex).

`EmbreeCaster` is the ray caster both halves share: the baker's `pipeline.tracing.Tracer` adds
surface attributes on top of it, and the relighter's exact shadows
(`relight_torch.visibility.rays.RayVisibility`) use it directly on a cache's occluder triangles.

Embreex facts this module relies on (embreex 4.4.0.post1, checked by the tests):
    * `EmbreeScene.run(origins, directions, dists, output=1)` returns a dict with 'u', 'v', 'Ng',
      'tfar', 'primID', 'geomID'; primID is -1 on a miss, where tfar keeps the input t_far. tnear
      is always 0.
    * It WRITES the hit distances back into `dists` for intersect queries, so we pass a copy.
    * `run` releases the GIL while tracing, so chunks traced on a thread pool run in parallel.
    * The only build option exposed is the robust flag (`robust=True`: watertight traversal,
      no cracks between triangles sharing an edge); build quality and the compact flag are not.
    * `TriangleMesh` copies the corners into Embree's own buffers (vertices padded to 16 bytes):
      a soup costs 60 bytes a triangle there, an indexed mesh 12 plus 16 per distinct corner
      (about 20 for a closed mesh), besides the BVH (about 64). Each mesh is one geometry; hits
      report its geomID and the primID within it.
    * There are no intersection filter callbacks: cut-outs and partial opacity
      (`relight_torch.visibility.opacity`) are traced as a second scene of the non-opaque
      triangles, whose hits are looked up and passed through in a bounded loop.
"""

from __future__ import annotations

import itertools
import os
import threading
from dataclasses import dataclass

import numpy as np
import torch
from embreex import mesh_construction, rtcore_scene

from relight_torch.io.mapped import release_pages
from relight_torch.lights.linking import linked_objects
from relight_torch.parallel import parallel_map
from relight_torch.visibility.opacity import OpacityTable, presence_random, ray_keys

# Rays per embreex call: bounds the temporary arrays of one chunk (~100 bytes per ray).
CHUNK_RAYS = 1 << 20
# Smallest chunk worth handing to another thread; below it the call overhead dominates.
MIN_THREAD_CHUNK_RAYS = 1 << 14
# Ray offset as a fraction of the scene's bounding-box diagonal.
EPSILON_DIAGONAL_FRACTION = 1e-4
# Ray offset in float32 ulps of the largest absolute coordinate, so that it survives rounding (and
# Embree's own intersection error) when the scene sits far from the origin.
EPSILON_ULPS = 32
# Triangles per Embree geometry: bounds the temporaries of indexing a block's shared corners, and
# the resident pages of a memory-mapped soup, which are given back block by block.
BUILD_BLOCK_TRIANGLES = 1 << 20
# Non-opaque surfaces one ray may pass through before it is stopped at the next (bounds the loop
# that continues rays through holes; a ray through a dense canopy crosses a few dozen leaves).
MAX_TRANSPARENT_LAYERS = 64


@dataclass(frozen=True)
class RayHits:
    """Closest hits of N rays, as the traversal reports them.

    Attributes:
        hit: (N,) bool, whether the ray hit a triangle before its t_far.
        distance: (N,) float32 ray parameter t of the hit (scene units for unit directions), inf on a miss.
        triangle_id: (N,) int32 index into the triangles, -1 on a miss.
        barycentrics: (N, 2) float32 Embree (u, v): weights of corners 1 and 2.
    """

    hit: np.ndarray
    distance: np.ndarray
    triangle_id: np.ndarray
    barycentrics: np.ndarray

    @property
    def num_rays(self) -> int:
        return int(self.hit.shape[0])


class EmbreeCaster:
    """Closest-hit and occlusion queries against a (T, 3, 3) float32 triangle soup.

    Args:
        corners: (T, 3, 3) float32 world-space triangle corners; kept by reference, not copied
            (Embree holds its own copy: a memory-mapped soup's pages are given back once read).
        num_threads: threads tracing chunks of a batch in parallel; default: the CPUs this
            process may use.
        epsilon: the ray offset; default: from the corners (below). A caster over a subset of a
            scene's triangles passes the whole scene's, so that its rays leave the same surfaces.
        opacity: the non-opaque triangles among those traced, or None.
        triangles: (K,) int64 ids of the triangles of `corners` to trace (default: all T); hits
            then report indices into this list (and `opacity` describes these K triangles).

    Attributes:
        epsilon: ray offset in scene units: the larger of 1e-4 x the bounding-box diagonal and 32
            float32 ulps of the largest coordinate. Use it through `offset_origins`.
    """

    def __init__(
        self,
        corners: np.ndarray,
        num_threads: int | None = None,
        epsilon: float | None = None,
        opacity: OpacityTable | None = None,
        triangles: np.ndarray | None = None,
    ):
        if corners.dtype != np.float32 or corners.ndim != 3 or corners.shape[1:] != (3, 3):
            raise ValueError(f"corners must be float32 (T, 3, 3), got {corners.dtype} {corners.shape}")
        self.num_threads = self.thread_count(num_threads)
        self.corners = corners
        self.opacity = opacity if opacity is not None and opacity.num_triangles else None
        # With cut-outs, two scenes: the opaque triangles (traced as before) and the others, whose
        # hits are tested with the opacity lookup and passed through in a bounded loop (embreex has
        # no filter callbacks). Each scene's hits index its own list of triangle ids.
        self._opaque_ids = self._clear_ids = self._clear_scene = None

        def of_corners(ids: np.ndarray | None) -> np.ndarray | None:
            """Traced triangles `ids` (default all) as ids into `corners`."""
            return ids if triangles is None else triangles if ids is None else triangles[ids]

        if self.opacity is not None:
            clear = self.opacity.transparent_mask(corners.shape[0] if triangles is None else triangles.shape[0])
            self._opaque_ids, self._clear_ids = np.flatnonzero(~clear), np.flatnonzero(clear)
            self._clear_scene = _TriangleScene(corners, of_corners(self._clear_ids))
        self._scene = _TriangleScene(corners, of_corners(self._opaque_ids))
        if epsilon is None:
            low, high = self._scene.bounds
            if self._clear_scene is not None:
                low, high = np.minimum(low, self._clear_scene.bounds[0]), np.maximum(high, self._clear_scene.bounds[1])
            epsilon = _bounds_epsilon(low, high)
        self.epsilon = epsilon

    @staticmethod
    def thread_count(num_threads: int | None) -> int:
        """`num_threads`, or every CPU this process may use when None."""
        return num_threads or len(os.sched_getaffinity(0))

    def intersect(self, origins: np.ndarray, directions: np.ndarray, t_far: np.ndarray | None = None) -> RayHits:
        """Closest hit of each ray: distance, triangle and barycentrics. Holes of cut-out and
        partially opaque triangles (`opacity`) are passed through.

        Args:
            origins: (N, 3) float32 world-space ray origins.
            directions: (N, 3) float32 world-space ray directions (need not be unit).
            t_far: (N,) float32 largest ray parameter to accept, or None for unbounded.

        Returns:
            `RayHits` of N rays.
        """
        num_rays = _check_rays(origins, directions, t_far)
        limit = np.full(num_rays, np.inf, np.float32) if t_far is None else t_far
        triangle_id, distance, barycentrics = self._closest(self._scene, origins, directions, limit)
        if self.opacity is not None:
            assert self._opaque_ids is not None  # split off with the opacity table in __init__
            hit = triangle_id >= 0
            triangle_id[hit] = self._opaque_ids[triangle_id[hit]]
            found, clear_id, clear_distance, clear_barycentrics = self._first_present(
                origins, directions, np.minimum(limit, distance)
            )
            triangle_id[found], distance[found], barycentrics[found] = clear_id, clear_distance, clear_barycentrics
        return RayHits(triangle_id >= 0, distance, triangle_id, barycentrics)

    def occluded(self, origins: np.ndarray, directions: np.ndarray, t_far: np.ndarray) -> np.ndarray:
        """Whether anything lies on each ray for t in [0, t_far] (Embree's any-hit query); holes of
        cut-out and partially opaque triangles (`opacity`) let the ray through.

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
            geometry_ids = self._scene.embree.run(
                origins[chunk], directions[chunk], dists=np.array(t_far[chunk], np.float32), query="OCCLUDED"
            )
            blocked[chunk] = geometry_ids != -1

        if self._scene.num_triangles:
            self._map_chunks(trace, num_rays)
        if self.opacity is not None:
            open_rays = np.flatnonzero(~blocked)
            blocked[open_rays] = self._first_present(origins[open_rays], directions[open_rays], t_far[open_rays])[0]
        return blocked

    def _closest(
        self, scene: _TriangleScene, origins: np.ndarray, directions: np.ndarray, t_far: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(triangle (N,) int64 into the scene's triangles, -1 on a miss; distance (N,) float32, inf
        on a miss; barycentrics (N, 2) float32) of the closest hits in one scene."""
        num_rays = origins.shape[0]
        distance = np.empty(num_rays, np.float32)
        triangle_id = np.empty(num_rays, np.int32)
        barycentrics = np.empty((num_rays, 2), np.float32)

        def trace(chunk: slice) -> None:
            raw = scene.embree.run(
                origins[chunk], directions[chunk], dists=np.array(t_far[chunk], np.float32), output=1
            )
            hit = raw["primID"] >= 0
            found = np.full(hit.shape, -1, np.int32)
            found[hit] = scene.first_triangle[raw["geomID"][hit]] + raw["primID"][hit]
            triangle_id[chunk] = found
            distance[chunk] = np.where(hit, raw["tfar"], np.inf)
            barycentrics[chunk, 0] = np.where(hit, raw["u"], 0)
            barycentrics[chunk, 1] = np.where(hit, raw["v"], 0)

        self._map_chunks(trace, num_rays)
        return triangle_id, distance, barycentrics

    def _first_present(
        self, origins: np.ndarray, directions: np.ndarray, limit: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The first hit among the non-opaque triangles that stops each ray before `limit` (N,).

        The rays restart just past each hit that lets them through (an `epsilon` further), at most
        MAX_TRANSPARENT_LAYERS times; a ray still going after that stops at its last hit.

        Returns:
            (found (N,) bool, and for the found rays: triangle ids (F,) int64, distances (F,)
            float32, barycentrics (F, 2) float32).
        """
        # Only called with an opacity table, which __init__ splits the clear triangles off with.
        assert self.opacity is not None and self._clear_ids is not None and self._clear_scene is not None
        num_rays = origins.shape[0]
        found = np.zeros(num_rays, bool)
        triangle_id = np.full(num_rays, -1, np.int64)
        distance = np.full(num_rays, np.inf, np.float32)
        barycentrics = np.zeros((num_rays, 2), np.float32)
        step = (self.epsilon / np.maximum(np.linalg.norm(directions, axis=-1), 1e-30)).astype(np.float32)
        start = np.zeros(num_rays, np.float32)
        live = np.arange(num_rays)
        for layer in range(MAX_TRANSPARENT_LAYERS):
            if live.size == 0:
                break
            moved = (origins[live] + directions[live] * start[live, None]).astype(np.float32)
            remaining = (limit[live] - start[live]).astype(np.float32)
            prim, t, uv = self._closest(self._clear_scene, moved, directions[live], remaining)
            hit = prim >= 0
            rays, ids = live[hit], self._clear_ids[prim[hit]]
            uv, t = uv[hit], start[rays] + t[hit]
            stops = self.opacity.present(
                torch.from_numpy(ids),
                torch.from_numpy(uv),
                presence_random(ray_keys(origins[rays], directions[rays], ids)),
            ).numpy()
            if layer == MAX_TRANSPARENT_LAYERS - 1:
                stops[:] = True
            found[rays[stops]] = True
            triangle_id[rays[stops]], distance[rays[stops]], barycentrics[rays[stops]] = ids[stops], t[stops], uv[stops]
            live = rays[~stops]
            start[live] = t[~stops] + step[live]
        return found, triangle_id[found], distance[found], barycentrics[found]

    def offset_origins(self, points: np.ndarray, normals: np.ndarray, directions: np.ndarray) -> np.ndarray:
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
        """Call `trace(chunk_slice)` over the batch, on the kept worker threads when it pays
        (`relight_torch.parallel`; inside a worker, on its thread)."""
        num_chunks = max(-(-num_rays // CHUNK_RAYS), min(self.num_threads, num_rays // MIN_THREAD_CHUNK_RAYS), 1)
        bounds = np.linspace(0, num_rays, num_chunks + 1).astype(np.int64)
        chunks = [slice(int(start), int(stop)) for start, stop in itertools.pairwise(bounds)]
        parallel_map(trace, chunks, self.num_threads)


class ShadowLinkCasters:
    """Casters over the occluders of each UsdLux shadow link: one Embree scene per distinct link,
    built when first asked for and kept.

    Args:
        corners: (T, 3, 3) float32 world-space occluder triangles.
        object_ids: (T,) int index of each triangle's object into `object_paths`.
        object_paths: the objects' prim paths, by object id.
        epsilon: the whole scene's ray offset (`EmbreeCaster.epsilon`).
        num_threads: as `EmbreeCaster`.
        opacity: the non-opaque triangles among `corners`, or None.
    """

    def __init__(
        self,
        corners: np.ndarray,
        object_ids: np.ndarray,
        object_paths: list[str],
        epsilon: float,
        num_threads: int | None = None,
        opacity: OpacityTable | None = None,
    ):
        if object_ids.shape != corners.shape[:1]:
            raise ValueError(f"object_ids must be ({corners.shape[0]},), got {object_ids.shape}")
        self.corners, self.object_ids, self.object_paths = corners, np.asarray(object_ids), object_paths
        self.epsilon, self.num_threads, self.opacity = epsilon, num_threads, opacity
        self._casters: dict[tuple[str, ...], EmbreeCaster] = {}
        self._lock = threading.Lock()  # tiles of points ask from several threads: build each once

    def __call__(self, link: tuple[str, ...]) -> EmbreeCaster:
        """The caster over the triangles of the objects in `link` (a `Light.shadow_link`)."""
        with self._lock:
            if link not in self._casters:
                keep = linked_objects(self.object_paths, link)[self.object_ids]
                opacity = None if self.opacity is None else self.opacity.subset(keep)
                self._casters[link] = EmbreeCaster(
                    self.corners, self.num_threads, self.epsilon, opacity, triangles=np.flatnonzero(keep)
                )
            return self._casters[link]


class _TriangleScene:
    """A committed embreex scene over the triangles `ids` (all if None) of a (T, 3, 3) float32 soup,
    added as indexed meshes of BUILD_BLOCK_TRIANGLES triangles each (`shared_corners`: the same
    triangles corner for corner, so the same hits as one soup mesh), a memory-mapped soup's pages
    given back after each block (`release_pages`).

    Attributes:
        embree: the committed `rtcore_scene.EmbreeScene`.
        first_triangle: (G,) int64 index, into the selected triangles, of each geometry's first
            triangle: a hit's triangle is first_triangle[geomID] + primID.
        num_triangles: the selected triangles' count.
        bounds: ((3,) low, (3,) high) float64 corners of the triangles' bounding box (+inf, -inf
            when there are none).
    """

    def __init__(self, corners: np.ndarray, ids: np.ndarray | None = None):
        self.num_triangles = int(corners.shape[0] if ids is None else ids.shape[0])
        self.embree = rtcore_scene.EmbreeScene(robust=True)
        self.first_triangle = np.arange(0, self.num_triangles, BUILD_BLOCK_TRIANGLES, dtype=np.int64)
        low, high = np.full(3, np.inf), np.full(3, -np.inf)
        for start in self.first_triangle.tolist():
            stop = min(start + BUILD_BLOCK_TRIANGLES, self.num_triangles)
            block = corners[start:stop] if ids is None else corners[ids[start:stop]]
            vertices, triangles = shared_corners(block)
            mesh_construction.TriangleMesh(self.embree, vertices, triangles)
            # float32 extremes are exact: no float64 copy of a big soup.
            low, high = np.minimum(low, vertices.min(axis=0)), np.maximum(high, vertices.max(axis=0))
            release_pages(block)
        # What reading the blocks mapped around them (the kernel maps pages near a fault, and a
        # selection reads its blocks by fancy indexing) goes too.
        release_pages(corners)
        self.bounds = low, high
        # An empty query commits (builds) the scene now rather than on the first real batch.
        self.embree.run(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32))


def shared_corners(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An indexed mesh of a (T, 3, 3) float32 soup: corners with the same bits become one vertex.

    Returns:
        (vertices (V, 3) float32, triangles (T, 3) int32) with vertices[triangles] == corners
        bit for bit (-0.0 and 0.0 stay apart). V is about T / 2 for a closed mesh.
    """
    points = np.ascontiguousarray(corners).reshape(-1, 3)
    if points.shape[0] == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32)
    bits = points.view(np.uint32)
    # Sort by (x, y) packed in 64 bits, then z: a 2-key lexsort is ~2x faster than np.unique on rows.
    xy = (bits[:, 0].astype(np.uint64) << np.uint64(32)) | bits[:, 1]
    order = np.lexsort((bits[:, 2], xy))
    xy, z = xy[order], bits[order, 2]
    first = np.ones(order.size, bool)
    first[1:] = (xy[1:] != xy[:-1]) | (z[1:] != z[:-1])
    vertex_of = np.empty(order.size, np.int32)
    vertex_of[order] = np.cumsum(first, dtype=np.int32) - 1
    return points[order[first]], vertex_of.reshape(-1, 3)


def _bounds_epsilon(low: np.ndarray, high: np.ndarray) -> float:
    """Ray offset for triangles within the box (low, high) (3,): see `Tracer.epsilon`. 0 for an
    empty box (low > high)."""
    if not np.all(low <= high):
        return 0.0
    diagonal = float(np.linalg.norm(high - low))
    magnitude = float(max(np.abs(low).max(), np.abs(high).max()))
    return max(EPSILON_DIAGONAL_FRACTION * diagonal, EPSILON_ULPS * float(np.spacing(np.float32(magnitude))))


def _check_rays(
    origins: np.ndarray, directions: np.ndarray, t_far: np.ndarray | None, t_far_required: bool = False
) -> int:
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
