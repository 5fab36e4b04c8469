"""Uniform subdivision of polygon meshes to their limit surface: Catmull-Clark and Loop.

A compact, vectorised refinement (no OpenSubdiv binding exists for Python): each level builds the
edge table of the current mesh and computes every new point with `np.bincount` gathers.

* Catmull-Clark (Catmull and Clark 1978) takes any polygons; one level makes them quads.
  Loop (Loop 1987) takes triangles only.
* Creases and corners follow DeRose, Kass and Truong (1998) with OpenSubdiv's "uniform" crease
  method: an edge of sharpness s >= 1 uses the sharp (midpoint) rule, 0 < s < 1 blends the smooth
  and sharp rules by s, and the children of an edge have sharpness s - 1. A vertex takes the smooth
  rule with fewer than two sharp edges, the crease rule (a + 6 v + b) / 8 with two, and stays put
  (corner) with more or with a vertex sharpness; where the rule changes between a level and the
  next the two are blended by the mean sharpness of what crossed zero (as OpenSubdiv does).
  Sharpness >= 10 is infinite (OpenSubdiv's SHARPNESS_INFINITE).
* Boundaries (`interpolateBoundary`): boundary and non-manifold edges are infinitely sharp;
  'edgeAndCorner' (USD's default) also makes a boundary vertex of a single face a corner.
  'none' is refined like 'edgeOnly' and its boundary faces are kept.
* After the last level every vertex is moved to its limit position with the limit stencil of its
  rule (Halstead, Kass and DeRose 1993 for Catmull-Clark; Loop 1987 for Loop; the cubic B-spline
  (a + 4 v + b) / 6 along creases and boundaries). A dart (one sharp edge at a vertex) takes the
  smooth limit mask, as OpenSubdiv does (not its exact limit). A semi-sharp edge still sharp after the last
  level is treated as sharp there (one more level would make it smooth).
* Normals: smooth interior vertices get the exact limit normal from the limit tangent masks
  (Halstead et al. 1993; Loop's cos/sin masks). Vertices on creases, boundaries and corners get,
  per corner, the area-weighted mean normal of the limit faces in their sector (the faces reached
  around the vertex without crossing a sharp edge), so hard creases shade hard.
* Face-varying data (uvs) are refined linearly (bilinear in each face), not with the
  face-varying boundary rules of OpenSubdiv (`faceVaryingLinearInterpolation` is not read).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

INFINITELY_SHARP = 10.0
"""Sharpness at and above which a crease or corner never softens."""


@dataclass(frozen=True)
class Cage:
    """A polygon mesh with what subdivision needs.

    Attributes:
        points: (V, 3) float64 positions.
        counts: (F,) int64 vertices per face (each >= 3).
        indices: (I,) int64 vertex of each face-vertex corner, faces in order.
        uvs: (I, 2) float64 uv per face-vertex corner, or None.
        face_ids: (F,) int64 authored face each face comes from.
        crease_edges: (K, 2) int64 vertex pairs of sharp edges (any order).
        crease_sharpness: (K,) float64 their sharpness (> 0; >= INFINITELY_SHARP is infinite).
        corner_sharpness: (V,) float64 vertex sharpness (0 for smooth vertices).
        corner_boundary: whether a boundary vertex of one face is a corner ('edgeAndCorner').
    """

    points: np.ndarray
    counts: np.ndarray
    indices: np.ndarray
    uvs: np.ndarray | None
    face_ids: np.ndarray
    crease_edges: np.ndarray
    crease_sharpness: np.ndarray
    corner_sharpness: np.ndarray
    corner_boundary: bool = True

    @property
    def num_points(self) -> int:
        return int(self.points.shape[0])


def make_cage(
    points,
    counts,
    indices,
    *,
    uvs=None,
    face_ids=None,
    crease_edges=None,
    crease_sharpness=None,
    corner_indices=None,
    corner_sharpness=None,
    interpolate_boundary: str = "edgeAndCorner",
) -> Cage:
    """A `Cage` from plain arrays (sharpness >= INFINITELY_SHARP becomes inf).

    Args:
        points: (V, 3). counts: (F,). indices: (I,). uvs: (I, 2) per corner or None.
        face_ids: (F,) or None for arange(F). crease_edges: (K, 2) vertex pairs or None.
        crease_sharpness: (K,). corner_indices: (J,) vertices. corner_sharpness: (J,).
        interpolate_boundary: 'edgeAndCorner', 'edgeOnly' or 'none'.
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    counts = np.asarray(counts, np.int64)
    edges = np.zeros((0, 2), np.int64) if crease_edges is None else np.asarray(crease_edges, np.int64)
    edge_sharpness = np.zeros(0) if crease_sharpness is None else np.asarray(crease_sharpness, np.float64)
    corners = np.zeros(len(points))
    if corner_indices is not None and len(corner_indices):
        np.maximum.at(corners, np.asarray(corner_indices, np.int64), np.asarray(corner_sharpness, np.float64))
    return Cage(
        points=points,
        counts=counts,
        indices=np.asarray(indices, np.int64),
        uvs=None if uvs is None else np.asarray(uvs, np.float64).reshape(-1, 2),
        face_ids=np.arange(counts.size, dtype=np.int64) if face_ids is None else np.asarray(face_ids, np.int64),
        crease_edges=edges.reshape(-1, 2),
        crease_sharpness=_infinite(edge_sharpness),
        corner_sharpness=_infinite(corners),
        corner_boundary=interpolate_boundary == "edgeAndCorner",
    )


def _infinite(sharpness: np.ndarray) -> np.ndarray:
    return np.where(sharpness >= INFINITELY_SHARP, np.inf, sharpness)


def _accumulate(ids: np.ndarray, values: np.ndarray, num_bins: int) -> np.ndarray:
    """Sum (N, C) `values` into `num_bins` bins by (N,) `ids` -> (num_bins, C) float64."""
    return np.stack(
        [np.bincount(ids, weights=values[:, c], minlength=num_bins) for c in range(values.shape[1])], axis=-1
    )


class _Topology:
    """Edge table and adjacency of a cage, everything as flat arrays.

    Attributes:
        face_of_corner, next_corner, prev_corner: (I,) per face-vertex corner.
        edges: (E, 2) sorted vertex pairs; edge_of_corner: (I,) the edge from a corner to the next.
        edge_faces: (E,) faces on each edge. vertex_faces, vertex_edges: (V,) counts.
        sharpness: (E,) edge sharpness (creases, inf on boundary and non-manifold edges).
        vertex_sharpness: (V,) corners (inf on single-face boundary vertices for 'edgeAndCorner').
    """

    def __init__(self, cage: Cage):
        counts, indices, num_points = cage.counts, cage.indices, cage.num_points
        starts = np.cumsum(counts) - counts
        self.face_of_corner = np.repeat(np.arange(counts.size), counts)
        position = np.arange(indices.size) - starts[self.face_of_corner]
        size = counts[self.face_of_corner]
        self.next_corner = starts[self.face_of_corner] + (position + 1) % size
        self.prev_corner = starts[self.face_of_corner] + (position - 1) % size
        a, b = indices, indices[self.next_corner]
        keys = np.minimum(a, b) * num_points + np.maximum(a, b)
        # One sort gives the edge table and, for manifold edges, the corner across each edge.
        order = np.argsort(keys, kind="stable")
        sorted_keys = keys[order]
        new_edge = np.concatenate(([True], sorted_keys[1:] != sorted_keys[:-1]))
        edge_keys = sorted_keys[new_edge]
        self.edge_of_corner = np.empty(indices.size, np.int64)
        self.edge_of_corner[order] = np.cumsum(new_edge) - 1
        self.edges = np.stack((edge_keys // num_points, edge_keys % num_points), axis=-1)
        self.edge_faces = np.bincount(self.edge_of_corner, minlength=len(edge_keys))
        pair = np.nonzero(self.edge_faces[self.edge_of_corner[order[:-1]]] == 2)[0]
        pair = pair[sorted_keys[pair] == sorted_keys[np.minimum(pair + 1, len(order) - 1)]]
        self.other_corner = np.full(indices.size, -1)
        self.other_corner[order[pair]] = order[pair + 1]
        self.other_corner[order[pair + 1]] = order[pair]
        self.vertex_faces = np.bincount(indices, minlength=num_points)
        self.vertex_edges = np.bincount(self.edges.ravel(), minlength=num_points)

        sharpness = np.zeros(len(edge_keys))
        if len(cage.crease_edges):
            lo, hi = np.sort(cage.crease_edges, axis=1).T
            crease_keys = lo * num_points + hi
            slot = np.clip(np.searchsorted(edge_keys, crease_keys), 0, max(len(edge_keys) - 1, 0))
            found = edge_keys[slot] == crease_keys  # creases naming no edge are ignored
            np.maximum.at(sharpness, slot[found], cage.crease_sharpness[found])
        sharpness[self.edge_faces != 2] = np.inf
        self.sharpness = sharpness
        vertex_sharpness = cage.corner_sharpness.copy()
        if cage.corner_boundary:
            vertex_sharpness[(self.vertex_faces == 1)] = np.inf
        self.vertex_sharpness = vertex_sharpness

    def follow(self, indices: np.ndarray) -> np.ndarray:
        """(I,) the corner at the same vertex in the next face around it (across the edge from the
        previous corner), -1 on boundaries, non-manifold edges and where the winding flips."""
        across = self.other_corner[self.prev_corner]
        return np.where((across >= 0) & (indices[np.maximum(across, 0)] == indices), across, -1)

    def rules(self, threshold: float) -> np.ndarray:
        """(V,) vertex rule where sharpness above `threshold` counts: 0 smooth, 1 crease, 2 corner."""
        sharp_edges = np.bincount(self.edges[self.sharpness > threshold].ravel(), minlength=self.vertex_faces.size)
        rule = np.minimum(np.where(sharp_edges < 2, 0, sharp_edges - 1), 2)
        return np.where(self.vertex_sharpness > threshold, 2, rule)

    def crease_neighbour_sum(self, points: np.ndarray, threshold: float) -> np.ndarray:
        """(V, 3) sum of the other ends of each vertex's edges sharper than `threshold`."""
        edges = self.edges[self.sharpness > threshold]
        ids = np.concatenate((edges[:, 0], edges[:, 1]))
        return _accumulate(ids, points[np.concatenate((edges[:, 1], edges[:, 0]))], len(points))

    def neighbour_sum(self, points: np.ndarray) -> np.ndarray:
        """(V, 3) sum of every vertex's edge neighbours."""
        ids = np.concatenate((self.edges[:, 0], self.edges[:, 1]))
        return _accumulate(ids, points[np.concatenate((self.edges[:, 1], self.edges[:, 0]))], len(points))


def _vertex_points(topology: _Topology, points: np.ndarray, smooth: np.ndarray) -> np.ndarray:
    """New positions of the old vertices from their smooth-rule positions (V, 3), with crease
    and corner rules and the fractional blend where the rule changes at this level."""

    def by_rule(rule: np.ndarray, threshold: float) -> np.ndarray:
        crease = (topology.crease_neighbour_sum(points, threshold) + 6.0 * points) / 8.0
        return np.where((rule == 0)[:, None], smooth, np.where((rule == 1)[:, None], crease, points))

    parent_rule, child_rule = topology.rules(0.0), topology.rules(1.0)
    parent = by_rule(parent_rule, 0.0)
    changed = parent_rule != child_rule
    if not changed.any():
        return parent
    # Fractional weight: the mean sharpness of the edges and corner that become smooth here.
    crossing = (topology.sharpness > 0) & (topology.sharpness <= 1)
    ends = topology.edges[crossing].ravel()
    total = np.bincount(ends, weights=np.repeat(topology.sharpness[crossing], 2), minlength=len(points))
    number = np.bincount(ends, minlength=len(points)).astype(np.float64)
    vertex = topology.vertex_sharpness
    vertex_crossing = (vertex > 0) & (vertex <= 1)
    total += np.where(vertex_crossing, vertex, 0.0)
    number += vertex_crossing
    weight = np.divide(total, number, out=np.ones_like(total), where=number > 0)[:, None]
    child = by_rule(child_rule, 1.0)
    return np.where(changed[:, None], weight * parent + (1.0 - weight) * child, parent)


def _edge_points(topology: _Topology, points: np.ndarray, smooth: np.ndarray) -> np.ndarray:
    """(E, 3) edge points: smooth-rule positions blended towards the midpoint by sharpness."""
    midpoint = points[topology.edges].mean(axis=1)
    weight = np.clip(topology.sharpness, 0.0, 1.0)[:, None]
    return (1.0 - weight) * smooth + weight * midpoint


def _child_creases(topology: _Topology, first_edge_point: int) -> tuple[np.ndarray, np.ndarray]:
    """Both halves of every edge that stays sharp, with sharpness s - 1 (uniform method)."""
    keep = topology.sharpness > 1.0
    edges = topology.edges[keep]
    middle = first_edge_point + np.nonzero(keep)[0]
    halves = np.concatenate((np.stack((edges[:, 0], middle), -1), np.stack((middle, edges[:, 1]), -1)))
    return halves, np.tile(topology.sharpness[keep] - 1.0, 2)


def catmull_clark_step(cage: Cage) -> Cage:
    """One Catmull-Clark level: every n-gon becomes n quads (vertex, edge, face, edge points)."""
    topology = _Topology(cage)
    points, indices = cage.points, cage.indices
    num_points, num_edges = len(points), len(topology.edges)
    face_points = _accumulate(topology.face_of_corner, points[indices], cage.counts.size) / cage.counts[:, None]

    # Edge points: (v0 + v1 + f0 + f1) / 4 = (midpoint + mean of the faces' points) / 2.
    midpoint = points[topology.edges].mean(axis=1)
    face_mean = (
        _accumulate(topology.edge_of_corner, face_points[topology.face_of_corner], num_edges)
        / np.maximum(topology.edge_faces, 1)[:, None]
    )
    edge_points = _edge_points(topology, points, (midpoint + face_mean) / 2.0)

    # Vertex points, smooth rule (Q + 2 R + (n - 3) v) / n with n edges, Q the mean of the
    # faces' points and R the mean of the edge midpoints.
    valence = np.maximum(topology.vertex_edges, 1)[:, None].astype(np.float64)
    q = (
        _accumulate(indices, face_points[topology.face_of_corner], num_points)
        / np.maximum(topology.vertex_faces, 1)[:, None]
    )
    r = (points + topology.neighbour_sum(points) / valence) / 2.0
    smooth = (q + 2.0 * r + (valence - 3.0) * points) / valence
    vertex_points = _vertex_points(topology, points, smooth)

    corner = np.arange(indices.size)
    quads = np.stack(
        (
            indices,
            num_points + topology.edge_of_corner,
            num_points + num_edges + topology.face_of_corner,
            num_points + topology.edge_of_corner[topology.prev_corner],
        ),
        axis=-1,
    )
    uvs = None
    if cage.uvs is not None:
        uv, uv_next, uv_prev = cage.uvs, cage.uvs[topology.next_corner], cage.uvs[topology.prev_corner]
        face_uv = _accumulate(topology.face_of_corner, uv, cage.counts.size) / cage.counts[:, None]
        uvs = np.stack((uv, (uv + uv_next) / 2, face_uv[topology.face_of_corner], (uv + uv_prev) / 2), axis=1).reshape(
            -1, 2
        )
    crease_edges, crease_sharpness = _child_creases(topology, num_points)
    return replace(
        cage,
        points=np.concatenate((vertex_points, edge_points, face_points)),
        counts=np.full(corner.size, 4, np.int64),
        indices=quads.reshape(-1),
        uvs=uvs,
        face_ids=cage.face_ids[topology.face_of_corner],
        crease_edges=crease_edges,
        crease_sharpness=crease_sharpness,
        corner_sharpness=np.concatenate(
            (np.maximum(cage.corner_sharpness - 1.0, 0.0), np.zeros(num_edges + cage.counts.size))
        ),
    )


def _loop_beta(valence: np.ndarray) -> np.ndarray:
    """Loop's vertex weight beta(n) = (5/8 - (3/8 + cos(2 pi / n) / 4)^2) / n."""
    n = np.maximum(valence, 1).astype(np.float64)
    return (5.0 / 8.0 - (3.0 / 8.0 + np.cos(2.0 * np.pi / n) / 4.0) ** 2) / n


def loop_step(cage: Cage) -> Cage:
    """One Loop level: every triangle becomes four (three corner triangles and the middle one)."""
    topology = _Topology(cage)
    points, indices = cage.points, cage.indices
    num_points, num_edges = len(points), len(topology.edges)

    # Edge points 3/8 (v0 + v1) + 1/8 (a + b), a and b opposite the edge in its two triangles.
    opposite = _accumulate(topology.edge_of_corner, points[indices[topology.prev_corner]], num_edges)
    edge_points = _edge_points(topology, points, 0.75 * points[topology.edges].mean(axis=1) + opposite / 8.0)

    beta = _loop_beta(topology.vertex_edges)[:, None]
    smooth = (1.0 - topology.vertex_edges[:, None] * beta) * points + beta * topology.neighbour_sum(points)
    vertex_points = _vertex_points(topology, points, smooth)

    v = indices.reshape(-1, 3)
    e = num_points + topology.edge_of_corner.reshape(-1, 3)  # e[:, k]: edge from corner k to k + 1
    triangles = np.stack(
        (
            np.stack((v[:, 0], e[:, 0], e[:, 2]), -1),
            np.stack((v[:, 1], e[:, 1], e[:, 0]), -1),
            np.stack((v[:, 2], e[:, 2], e[:, 1]), -1),
            e,
        ),
        axis=1,
    )
    uvs = None
    if cage.uvs is not None:
        uv = cage.uvs.reshape(-1, 3, 2)
        mid = (uv + np.roll(uv, -1, axis=1)) / 2  # mid[:, k]: middle of edge k -> k + 1
        uvs = np.stack(
            (
                np.stack((uv[:, 0], mid[:, 0], mid[:, 2]), 1),
                np.stack((uv[:, 1], mid[:, 1], mid[:, 0]), 1),
                np.stack((uv[:, 2], mid[:, 2], mid[:, 1]), 1),
                mid,
            ),
            axis=1,
        ).reshape(-1, 2)
    crease_edges, crease_sharpness = _child_creases(topology, num_points)
    return replace(
        cage,
        points=np.concatenate((vertex_points, edge_points)),
        counts=np.full(4 * len(v), 3, np.int64),
        indices=triangles.reshape(-1),
        uvs=uvs,
        face_ids=np.repeat(cage.face_ids, 4),
        crease_edges=crease_edges,
        crease_sharpness=crease_sharpness,
        corner_sharpness=np.concatenate((np.maximum(cage.corner_sharpness - 1.0, 0.0), np.zeros(num_edges))),
    )


# ---------------------------------------------------------------------------------------------
# The limit surface at the vertices of the last level


def _ring_indices(cage: Cage, topology: _Topology, closed: np.ndarray) -> np.ndarray:
    """(I,) position of each corner in the counter-clockwise order of the faces around its vertex,
    -1 where the vertex is not in `closed` (V,) or its ring does not close (non-manifold)."""
    indices = cage.indices
    num_points = cage.num_points
    follow = topology.follow(indices)
    _, first_corner = np.unique(indices, return_index=True)
    starts = first_corner[closed[indices[first_corner]]]
    ring = np.full(indices.size, -1)
    current = starts
    valence = topology.vertex_faces[indices[starts]]
    for step in range(int(valence.max(initial=0))):
        active = (step < valence) & (current >= 0)
        ring[current[active]] = step
        current = np.where(active, follow[np.maximum(current, 0)], current)
    # A ring is valid when the walk came back to its start after exactly `valence` steps.
    valid = np.zeros(num_points, bool)
    valid[indices[starts]] = current == starts
    return np.where(valid[indices], ring, -1)


def _sector_normals(cage: Cage, topology: _Topology, points: np.ndarray) -> np.ndarray:
    """(I, 3) per corner: the area-weighted sum of the normals of the faces around the corner's
    vertex reachable without crossing a sharp edge (its sector; the whole ring where the vertex
    has no sharp edge)."""
    indices = cage.indices
    num_points = cage.num_points
    p = points[indices]
    # Face normal = sum over corners of p x p_next (Newell), |.| = 2 area for planar faces.
    face_normals = _accumulate(
        topology.face_of_corner, np.cross(p, points[indices[topology.next_corner]]), cage.counts.size
    )
    has_sharp = np.bincount(topology.edges[topology.sharpness > 0].ravel(), minlength=num_points) > 0
    # Labels: a vertex id for corners of vertices without sharp edges, else num_points + a corner
    # id propagated around the vertex across its smooth edges (the smallest id of the sector).
    label = np.where(has_sharp[indices], num_points + np.arange(indices.size), indices)
    follow = topology.follow(indices)
    crossing_sharp = topology.sharpness[topology.edge_of_corner[topology.prev_corner]] > 0
    linked = np.nonzero(has_sharp[indices] & (follow >= 0) & ~crossing_sharp)[0]
    targets = follow[linked]
    for _ in range(int(topology.vertex_faces.max(initial=0)) + 1):
        low = np.minimum(label[linked], label[targets])
        if np.array_equal(low, label[linked]) and np.array_equal(low, label[targets]):
            break
        label[linked] = low  # each corner has one follower and one predecessor: no collisions
        label[targets] = np.minimum(label[targets], low)
    sums = _accumulate(label, face_normals[topology.face_of_corner], num_points + indices.size)
    return sums[label]


def limit_surface(cage: Cage, scheme: str) -> tuple[np.ndarray, np.ndarray]:
    """Limit positions of the vertices and limit normals per corner of an all-quad (Catmull-Clark)
    or all-triangle (Loop) cage, i.e. one refined at least once.

    Returns:
        positions (V, 3) float64, normals (I, 3) float64 unit (oriented with the face winding).
    """
    topology = _Topology(cage)
    points, indices = cage.points, cage.indices
    num_points = len(points)
    rule = topology.rules(0.0)
    n = np.maximum(topology.vertex_edges, 1).astype(np.float64)[:, None]
    neighbours = topology.neighbour_sum(points)
    if scheme == "catmullClark":
        diagonal = _accumulate(indices, points[indices[topology.next_corner[topology.next_corner]]], num_points)
        smooth = (n * n * points + 4.0 * neighbours + diagonal) / (n * (n + 5.0))
    else:
        beta = _loop_beta(topology.vertex_edges)[:, None]
        chi = 1.0 / (3.0 / (8.0 * beta) + n)
        smooth = (1.0 - n * chi) * points + chi * neighbours
    crease = (topology.crease_neighbour_sum(points, 0.0) + 4.0 * points) / 6.0
    limit = np.where((rule == 0)[:, None], smooth, np.where((rule == 1)[:, None], crease, points))

    normals = _sector_normals(cage, topology, limit)
    interior = (rule == 0) & (topology.vertex_faces == topology.vertex_edges)
    ring = _ring_indices(cage, topology, interior)
    corner = np.nonzero(ring >= 0)[0]
    valence = topology.vertex_faces[indices[corner]]
    # Mask weights tabulated per (valence, ring position): cos and sin of 2 pi i / n.
    n_table = np.arange(int(valence.max(initial=2)) + 1, dtype=np.float64)[:, None]
    angles = 2.0 * np.pi * np.arange(n_table.size + 1)[None, :] / np.maximum(n_table, 1)
    cos_table, sin_table = np.cos(angles), np.sin(angles)
    ring_at = ring[corner]
    cos_i, sin_i = cos_table[valence, ring_at][:, None], sin_table[valence, ring_at][:, None]
    edge_neighbour = points[indices[topology.next_corner[corner]]]
    if scheme == "catmullClark":
        c1 = np.cos(2 * np.pi / np.maximum(n_table[:, 0], 1))
        a_table = 1.0 + c1 + np.cos(np.pi / np.maximum(n_table[:, 0], 1)) * np.sqrt(2.0 * (9.0 + c1))
        a = a_table[valence][:, None]
        cos_next, sin_next = cos_table[valence, ring_at + 1][:, None], sin_table[valence, ring_at + 1][:, None]
        diagonal = points[indices[topology.next_corner[topology.next_corner[corner]]]]
        t1 = a * cos_i * edge_neighbour + (cos_i + cos_next) * diagonal
        t2 = a * sin_i * edge_neighbour + (sin_i + sin_next) * diagonal
    else:
        t1 = cos_i * edge_neighbour
        t2 = sin_i * edge_neighbour
    vertex = indices[corner]
    tangent_normal = np.cross(_accumulate(vertex, t1, num_points), _accumulate(vertex, t2, num_points))[vertex]
    # Orient the exact normal with the faces' winding (the ring runs against it).
    sign = np.where(np.sum(tangent_normal * normals[corner], axis=-1) < 0, -1.0, 1.0)[:, None]
    usable = np.linalg.norm(tangent_normal, axis=-1) > 0
    normals[corner[usable]] = (sign * tangent_normal)[usable]
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    return limit, np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)


def step(cage: Cage, scheme: str) -> Cage:
    """One level of `scheme` ('catmullClark' or 'loop'; Loop needs triangles)."""
    if scheme == "catmullClark":
        return catmull_clark_step(cage)
    if scheme != "loop":
        raise ValueError(f"unknown subdivision scheme {scheme!r}")
    if np.any(cage.counts != 3):
        raise ValueError("Loop subdivision needs a triangle mesh")
    return loop_step(cage)


def limit_triangles(cage: Cage, limit: np.ndarray, normals: np.ndarray) -> dict[str, np.ndarray]:
    """The refined cage's faces as triangles at their limit positions.

    Args:
        cage: an all-quad or all-triangle refined cage. limit: (V, 3) and normals: (I, 3) from
            `limit_surface`.

    Returns:
        positions (T, 3, 3), normals (T, 3, 3), uvs (T, 3, 2) (absent without uvs), face_ids (T,):
        counter-clockwise as the cage's faces; quads are split along their 0-2 diagonal.
    """
    size = int(cage.counts[0])
    corners = np.arange(cage.indices.size).reshape(-1, size)
    if size == 4:
        corners = corners[:, [0, 1, 2, 0, 2, 3]].reshape(-1, 3)
    result = {
        "positions": limit[cage.indices[corners]],
        "normals": normals[corners],
        "face_ids": np.repeat(cage.face_ids, size - 2),
    }
    if cage.uvs is not None:
        result["uvs"] = cage.uvs[corners]
    return result


def refined_triangles(cage: Cage, scheme: str, levels: int) -> dict[str, np.ndarray]:
    """Refine `levels` (>= 1) times and return the limit surface as triangles (`limit_triangles`)."""
    if levels < 1:
        raise ValueError(f"subdivision needs at least one level, got {levels}")
    for _ in range(levels):
        cage = step(cage, scheme)
    return limit_triangles(cage, *limit_surface(cage, scheme))


def triangle_count(counts: np.ndarray, scheme: str, levels: int) -> int:
    """Triangles `refined_triangles` makes from faces of `counts` at `levels` (>= 1)."""
    if scheme == "loop":
        return int(counts.size * 4**levels)
    return int(2 * counts.sum() * 4 ** (levels - 1))
