"""Where visibility cuts are stored: the vertices of the seen triangles, refined where too coarse.

Cheslack-Postava et al. 2008 store a visibility cut per mesh vertex and interpolates the three cuts of a pixel's
triangle with its barycentric weights. Meshes may be far too coarse for that (the glossy floor is
two triangles), so every triangle the camera sees is subdivided into an n x n lattice of
sub-triangles, n = ceil(longest edge / target edge) (capped), and each lattice vertex gets a cut.
Lattice vertex (i, j), i + j <= n, lies at barycentrics (u, v) = (i / n, j / n) (Embree's: the
weights of corners 1 and 2), numbered i (n + 1) - i (i - 1) / 2 + j within its triangle. Only the
triangles some sub-sample hits are refined; vertices are not shared between triangles (a shared
edge gets the same cuts twice, at the same points when both sides have the same n).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Lattice:
    """The refined vertices and how the view's sub-samples interpolate them.

    Attributes:
        position: (V, 3) float32 world position of each lattice vertex.
        normal: (V, 3) float32 unit geometric normal of its triangle, on the camera's side.
        sample_vertices: (N, 3) int64 the three lattice vertices around each covered sub-sample.
        sample_weights: (N, 3) float32 their barycentric weights (sum 1).
    """

    position: np.ndarray
    normal: np.ndarray
    sample_vertices: np.ndarray
    sample_weights: np.ndarray

    @property
    def num_vertices(self) -> int:
        return int(self.position.shape[0])


def _lattice_index(i: np.ndarray, j: np.ndarray, n: np.ndarray) -> np.ndarray:
    return i * (n + 1) - i * (i - 1) // 2 + j


def build_lattice(
    corners: np.ndarray,
    triangle_id: np.ndarray,
    barycentrics: np.ndarray,
    camera_position: np.ndarray,
    target_edge: float,
    max_subdivisions: int = 64,
) -> Lattice:
    """Refine the triangles the sub-samples hit and place each sub-sample among the lattice vertices.

    Args:
        corners: (T, 3, 3) float32 world triangles (the scene's soup).
        triangle_id: (N,) int32 triangle hit by each covered sub-sample.
        barycentrics: (N, 2) float32 Embree (u, v) of each hit.
        camera_position: (3,) world position (orients the normals).
        target_edge: longest sub-triangle edge wanted, world units (> 0).
        max_subdivisions: cap on n per triangle.
    """
    if target_edge <= 0:
        raise ValueError(f"the lattice's target edge must be > 0, got {target_edge}")
    used, local = np.unique(triangle_id, return_inverse=True)
    tri = corners[used].astype(np.float64)
    edges = np.stack((tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 1], tri[:, 0] - tri[:, 2]), axis=1)
    longest = np.linalg.norm(edges, axis=-1).max(axis=1)
    n = np.clip(np.ceil(longest / target_edge), 1, max_subdivisions).astype(np.int64)
    counts = (n + 1) * (n + 2) // 2
    offsets = np.concatenate(([0], np.cumsum(counts)[:-1]))

    owner = np.repeat(np.arange(used.shape[0]), counts)
    q = np.arange(owner.shape[0]) - offsets[owner]
    n_owner = n[owner]
    # Row i of lattice vertex q: the largest i with lattice_index(i, 0, n) <= q.
    b = 2 * n_owner + 3
    i = np.floor((b - np.sqrt(np.maximum(b * b - 8.0 * q, 0.0))) / 2.0).astype(np.int64)
    i = np.where(_lattice_index(i, 0, n_owner) > q, i - 1, i)
    i = np.where(_lattice_index(i + 1, 0, n_owner) <= q, i + 1, i)
    j = q - _lattice_index(i, 0, n_owner)
    u, v = i / n_owner, j / n_owner
    t = tri[owner]
    position = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])

    face = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    face /= np.maximum(np.linalg.norm(face, axis=-1, keepdims=True), 1e-30)
    towards_camera = np.einsum("tk,tk->t", face, np.asarray(camera_position, np.float64) - tri[:, 0])
    face *= np.where(towards_camera < 0, -1.0, 1.0)[:, None]

    n_sample = n[local]
    a = barycentrics[:, 0].astype(np.float64) * n_sample
    c = barycentrics[:, 1].astype(np.float64) * n_sample
    si = np.clip(np.floor(a), 0, n_sample - 1).astype(np.int64)
    sj = np.clip(np.floor(c), 0, n_sample - 1 - si).astype(np.int64)
    fa, fc = a - si, c - sj
    upper = (fa + fc > 1.0) & (si + sj <= n_sample - 2)
    base = offsets[local]
    lower_vertices = np.stack(
        (_lattice_index(si, sj, n_sample), _lattice_index(si + 1, sj, n_sample), _lattice_index(si, sj + 1, n_sample)),
        axis=1,
    )
    upper_vertices = np.stack(
        (
            _lattice_index(si + 1, sj + 1, n_sample),
            _lattice_index(si, sj + 1, n_sample),
            _lattice_index(si + 1, sj, n_sample),
        ),
        axis=1,
    )
    lower_weights = np.stack((1.0 - fa - fc, fa, fc), axis=1)
    upper_weights = np.stack((fa + fc - 1.0, 1.0 - fa, 1.0 - fc), axis=1)
    vertices = np.where(upper[:, None], upper_vertices, lower_vertices) + base[:, None]
    weights = np.clip(np.where(upper[:, None], upper_weights, lower_weights), 0.0, 1.0)
    weights /= np.maximum(weights.sum(axis=1, keepdims=True), 1e-12)
    return Lattice(position.astype(np.float32), face[owner].astype(np.float32), vertices, weights.astype(np.float32))
