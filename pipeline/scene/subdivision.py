"""Subdivision-surface meshes of a stage: their cage as USD authors it, the level, the surface.

A Mesh whose `subdivisionScheme` is 'catmullClark' or 'loop' is rendered as its limit surface,
refined uniformly (`subdivide`) to the level `dicing` picks from the stage's cameras. Read here:
`creaseIndices` / `creaseLengths` / `creaseSharpnesses` (one sharpness per crease, or one per
crease edge), `cornerIndices` / `cornerSharpnesses`, `interpolateBoundary`, `orientation`, and
`st` (any interpolation, refined linearly per face). Authored normals are ignored, as the UsdGeom
schema says for subdivision surfaces. 'bilinear' meshes render as their cage (their limit is the
bilinear cage). A 'loop' mesh with non-triangular faces is refined with Catmull-Clark (warned).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pxr import Usd, UsdGeom

from pipeline.errors import warn
from pipeline.scene import dicing
from pipeline.scene.primvars import Triangulation
from pipeline.scene.subdivide import Cage, limit_surface, limit_triangles, make_cage, step, triangle_count
from pipeline.scene.tessellate import Surface, corner_values, mesh_topology, uv_primvar

SCHEMES = ("catmullClark", "loop")


@dataclass(frozen=True)
class SubdivisionMesh:
    """A subdivision mesh's cage, read once and refined at the levels its placements need.

    Attributes:
        path: the mesh prim's path (for warnings).
        scheme: 'catmullClark' or 'loop'.
        cage: the control mesh (wound counter-clockwise from the front; `leftHanded` reversed).
        edges: (E, 2) int64 the cage's edges (for the level choice).
        num_faces: authored faces.
        has_uvs: whether `st` was read.
    """

    path: str
    scheme: str
    cage: Cage
    edges: np.ndarray
    num_faces: int
    has_uvs: bool


def is_subdivision(mesh: UsdGeom.Mesh, time: Usd.TimeCode) -> bool:
    """Whether the mesh is a Catmull-Clark or Loop subdivision surface."""
    return mesh.GetSubdivisionSchemeAttr().Get(time) in SCHEMES


def _creases(mesh: UsdGeom.Mesh, time: Usd.TimeCode, warnings: list[str]):
    """(edges (K, 2), sharpness (K,)) of the authored creases; empty (warned) when inconsistent."""
    indices = np.asarray(mesh.GetCreaseIndicesAttr().Get(time) or [], np.int64)
    lengths = np.asarray(mesh.GetCreaseLengthsAttr().Get(time) or [], np.int64)
    sharpness = np.asarray(mesh.GetCreaseSharpnessesAttr().Get(time) or [], np.float64)
    empty = np.zeros((0, 2), np.int64), np.zeros(0)
    if indices.size == 0:
        return empty
    num_edges = int(np.maximum(lengths - 1, 0).sum())
    if lengths.sum() != indices.size or (lengths < 2).any() or sharpness.size not in (lengths.size, num_edges):
        warn(
            f"mesh {mesh.GetPath()}: creaseIndices/creaseLengths/creaseSharpnesses do not agree; creases ignored",
            warnings,
        )
        return empty
    starts = np.cumsum(lengths) - lengths
    crease_of_edge = np.repeat(np.arange(lengths.size), lengths - 1)
    first_edge = np.cumsum(lengths - 1) - (lengths - 1)
    first = starts[crease_of_edge] + np.arange(num_edges) - first_edge[crease_of_edge]  # chain's k-th vertex
    edges = np.stack((indices[first], indices[first + 1]), axis=-1)
    # One sharpness per edge when the counts say so (per crease when both readings coincide).
    per_edge = sharpness if sharpness.size == num_edges else sharpness[crease_of_edge]
    keep = per_edge > 0
    return edges[keep], per_edge[keep]


def _corners(mesh: UsdGeom.Mesh, time: Usd.TimeCode, warnings: list[str]):
    """(indices (J,), sharpness (J,)) of the authored corners; empty (warned) when inconsistent."""
    indices = np.asarray(mesh.GetCornerIndicesAttr().Get(time) or [], np.int64)
    sharpness = np.asarray(mesh.GetCornerSharpnessesAttr().Get(time) or [], np.float64)
    if indices.size != sharpness.size:
        warn(f"mesh {mesh.GetPath()}: cornerIndices and cornerSharpnesses differ in length; corners ignored", warnings)
        return np.zeros(0, np.int64), np.zeros(0)
    return indices, sharpness


def read_subdivision_mesh(mesh: UsdGeom.Mesh, time: Usd.TimeCode, warnings: list[str]) -> SubdivisionMesh | None:
    """The cage of a subdivision mesh, or None when it cannot be subdivided (empty or invalid
    topology, left to the caller's `mesh_surface` to warn about; faces of fewer than 3 vertices,
    a vertex repeated along a face, or non-finite points, warned): the caller then renders the
    cage, dropping its degenerate triangles."""
    topology_warnings: list[str] = []
    topology = mesh_topology(mesh, time, topology_warnings)
    if topology is None:
        return None  # the caller's `mesh_surface` reads the same topology and warns
    warnings.extend(topology_warnings)
    points, counts, indices = topology
    path = str(mesh.GetPath())
    if (counts < 3).any():
        warn(f"mesh {path}: faces with fewer than 3 vertices cannot be subdivided; the cage is rendered", warnings)
        return None
    if not np.isfinite(points).all():
        warn(f"mesh {path}: non-finite points cannot be subdivided; the cage is rendered", warnings)
        return None
    following = np.arange(indices.size) + 1
    following[np.cumsum(counts) - 1] = np.cumsum(counts) - counts
    if (indices == indices[following]).any():
        warn(f"mesh {path}: faces with a repeated vertex cannot be subdivided; the cage is rendered", warnings)
        return None
    scheme = str(mesh.GetSubdivisionSchemeAttr().Get(time))
    if scheme == "loop" and (counts != 3).any():
        warn(f"mesh {path}: Loop subdivision needs triangles; refined with Catmull-Clark", warnings)
        scheme = "catmullClark"
    face_of_corner = np.repeat(np.arange(counts.size), counts)
    corner = np.arange(indices.size)
    if mesh.GetOrientationAttr().Get(time) == UsdGeom.Tokens.leftHanded:
        # Reverse every face, keeping its first vertex: corner k -> (n - k) mod n.
        starts = np.cumsum(counts) - counts
        position = corner - starts[face_of_corner]
        corner = starts[face_of_corner] + (-position) % counts[face_of_corner]
    prim = mesh.GetPrim()
    # One "triangle" of one corner per face-vertex: expands any interpolation per corner.
    per_corner = Triangulation(corner[:, None], face_of_corner)
    uvs = corner_values(prim, "st", uv_primvar(prim, time), per_corner, indices, warnings)
    has_uvs = uvs is not None and uvs.shape[-1] == 2
    crease_edges, crease_sharpness = _creases(mesh, time, warnings)
    corner_indices, corner_sharpness = _corners(mesh, time, warnings)
    cage = make_cage(
        points,
        counts,
        indices[corner],
        uvs=uvs.reshape(-1, 2) if has_uvs else None,
        crease_edges=crease_edges,
        crease_sharpness=crease_sharpness,
        corner_indices=corner_indices,
        corner_sharpness=corner_sharpness,
        interpolate_boundary=str(mesh.GetInterpolateBoundaryAttr().Get(time)),
    )
    pairs = np.sort(np.stack((cage.indices, cage.indices[following]), axis=-1), axis=1)
    return SubdivisionMesh(
        path=path, scheme=scheme, cage=cage, edges=np.unique(pairs, axis=0), num_faces=int(counts.size), has_uvs=has_uvs
    )


class Refinement:
    """A subdivision mesh's levels, refined on demand and kept, so that every placement (and
    every instance proxy of one prototype) shares them.

    The level for a set of placements is the coarser of two screen-space criteria (`dicing`):
    cage edges halved under `dicing.EDGE_PIXELS`, or, from level 1 on, every vertex within
    `dicing.FLAT_PIXELS` of its limit position along the normal (the facets then deviate from
    the limit surface by less than that; planar cages stop at level 1, with or without
    cameras); capped by the budget.
    """

    def __init__(self, mesh: SubdivisionMesh):
        self.mesh = mesh
        self._cages = [mesh.cage]
        self._limits: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._deviations: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._surfaces: dict[int, Surface] = {}

    def _cage(self, level: int) -> Cage:
        while len(self._cages) <= level:
            self._cages.append(step(self._cages[-1], self.mesh.scheme))
        return self._cages[level]

    def _limit(self, level: int) -> tuple[np.ndarray, np.ndarray]:
        if level not in self._limits:
            self._limits[level] = limit_surface(self._cage(level), self.mesh.scheme)
        return self._limits[level]

    def _deviation(self, level: int) -> tuple[np.ndarray, np.ndarray]:
        """(V, 3) control points of `level` and their projections towards the limit along the
        vertex normal (segments whose length is the distance to the limit surface)."""
        if level not in self._deviations:
            self._deviations[level] = self._compute_deviation(level)
        return self._deviations[level]

    def _compute_deviation(self, level: int) -> tuple[np.ndarray, np.ndarray]:
        cage = self._cage(level)
        limit, normals = self._limit(level)
        vertex_normals = np.zeros_like(limit)
        np.add.at(vertex_normals, cage.indices, normals)
        length = np.linalg.norm(vertex_normals, axis=-1, keepdims=True)
        vertex_normals = np.divide(vertex_normals, length, out=np.zeros_like(vertex_normals), where=length > 0)
        along = np.sum((limit - cage.points) * vertex_normals, axis=-1, keepdims=True)
        return cage.points, cage.points + along * vertex_normals

    def _flatness(self, level: int, world_from_local: np.ndarray, views: list[dicing.View]) -> np.ndarray:
        """(I,) how far the control points of `level` are from the limit, over the tolerance, per
        placement: the projected distance / `dicing.FLAT_PIXELS`, or without cameras the distance /
        1e-6 of the cage's size (only a flat cage stops early)."""
        starts, ends = self._deviation(level)
        if views:
            return dicing.projected_lengths(starts, ends, world_from_local, views) / dicing.FLAT_PIXELS
        size = float(np.ptp(self.mesh.cage.points, axis=0).max(initial=0.0))
        distance = float(np.linalg.norm(ends - starts, axis=-1).max(initial=0.0))
        return np.full(len(world_from_local), distance / (1e-6 * size) if size > 0 else 0.0)

    def choose_levels(self, world_from_local: np.ndarray, views: list[dicing.View]) -> tuple[np.ndarray, str | None]:
        """The level of each of I placements (I, 4, 4) seen by `views` (empty: the fallback level),
        and a warning when the triangle budget cut one; 0 means the cage (no level fits the budget).

        Returns:
            ((I,) int64 levels, warning or None).
        """
        mesh = self.mesh
        count = len(world_from_local)
        pixels = None
        if views:
            pixels = dicing.projected_lengths(
                mesh.cage.points[mesh.edges[:, 0]], mesh.cage.points[mesh.edges[:, 1]], world_from_local, views
            )
            wanted = np.maximum(1, dicing.levels_for_pixels(pixels))
        else:
            wanted = np.full(count, dicing.FALLBACK_LEVEL, np.int64)
        cap = int(wanted.max(initial=0))
        while cap >= 1 and triangle_count(mesh.cage.counts, mesh.scheme, cap) > dicing.TRIANGLE_BUDGET:
            cap -= 1
        levels = np.minimum(wanted, cap)
        # The distance to the limit shrinks about 4x a level (quadratic convergence): predict each
        # placement's flat level from level 1's, then confirm it on the level itself (its limit is
        # needed anyway). Placements are visited in groups at the same trial level.
        chosen = levels.copy()
        trial = np.ones(count, np.int64)
        pending = trial < levels
        while pending.any():
            flat_level = int(trial[pending].min())
            rows = np.flatnonzero(pending & (trial == flat_level))
            excess = self._flatness(flat_level, world_from_local[rows], views)
            flat = excess <= 1.0
            chosen[rows[flat]] = flat_level
            pending[rows[flat]] = False
            rows, excess = rows[~flat], excess[~flat]
            steps = np.ceil(np.minimum(np.log(excess) / np.log(4), dicing.MAX_LEVEL)).astype(np.int64)
            trial[rows] = np.minimum(levels[rows], np.maximum(flat_level + 1, flat_level + steps))
            pending[rows] = trial[rows] < levels[rows]
        cut = np.flatnonzero((chosen == levels) & (levels < wanted) & (levels >= 1))
        if cut.size:
            still_rough = self._flatness(cap, world_from_local[cut], views) > 1.0
            cut = cut[still_rough]
        elif cap < 1:
            cut = np.flatnonzero(levels < wanted)
        if cut.size == 0:
            return chosen, None
        most = int(wanted[cut].max())
        reached = "" if pixels is None else f" (edges up to {float(pixels[cut].max()) / 2**cap:.1f} pixels)"
        return chosen, (
            f"mesh {mesh.path}: subdivision level {most} would make "
            f"{triangle_count(mesh.cage.counts, mesh.scheme, most):,} triangles, over the budget "
            f"of {dicing.TRIANGLE_BUDGET:,} per mesh; refined to level {cap}{reached}"
        )

    def surface(self, level: int) -> Surface:
        """The limit surface refined `level` (>= 1) times, as a `Surface`."""
        if level not in self._surfaces:
            refined = limit_triangles(self._cage(level), *self._limit(level))
            positions = refined["positions"]
            uvs = refined["uvs"] if self.mesh.has_uvs else np.zeros(positions.shape[:2] + (2,))
            self._surfaces[level] = Surface(
                positions=positions.astype(np.float32),
                normals=refined["normals"].astype(np.float32),
                uvs=uvs.astype(np.float32),
                face_ids=refined["face_ids"],
                num_faces=self.mesh.num_faces,
            )
        return self._surfaces[level]
