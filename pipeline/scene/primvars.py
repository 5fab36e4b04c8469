"""Mesh topology to triangles, and primvars to per-triangle-corner values.

A mesh face with n vertices becomes the fan (0, k+1, k+2), k < n - 2, of its face-vertex
"corners" (positions in `faceVertexIndices`). Every primvar is then gathered per triangle corner
according to its interpolation, so the result is the (T, 3, C) layout of `Geometry`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pxr import Usd, UsdGeom


@dataclass(frozen=True)
class Triangulation:
    """Fan triangulation of a polygon mesh.

    Attributes:
        corners: (T, 3) int64 index into `faceVertexIndices` of each triangle corner.
        face_ids: (T,) int64 index of the authored face each triangle comes from.
    """

    corners: np.ndarray
    face_ids: np.ndarray

    @property
    def num_triangles(self) -> int:
        return int(self.corners.shape[0])


def triangulate(face_vertex_counts: np.ndarray) -> Triangulation:
    """Fan-triangulate faces of any vertex count (faces with fewer than 3 vertices give none).

    Args:
        face_vertex_counts: (F,) int vertex count of each face.

    Returns:
        The triangulation; triangles of a face are consecutive and faces stay in order.
    """
    counts = np.asarray(face_vertex_counts, np.int64)
    starts = np.concatenate(([0], np.cumsum(counts)[:-1])) if counts.size else counts
    triangles_per_face = np.maximum(counts - 2, 0)
    face_ids = np.repeat(np.arange(counts.size, dtype=np.int64), triangles_per_face)
    # k-th triangle of its face: offset of this triangle within the face's run.
    first_triangle = np.cumsum(triangles_per_face) - triangles_per_face
    k = np.arange(face_ids.size, dtype=np.int64) - first_triangle[face_ids]
    start = starts[face_ids]
    corners = np.stack((start, start + k + 1, start + k + 2), axis=-1)
    return Triangulation(corners=corners, face_ids=face_ids)


def expand(
    values: np.ndarray, interpolation: str, triangulation: Triangulation, face_vertex_indices: np.ndarray
) -> np.ndarray | None:
    """Gather primvar values per triangle corner.

    Args:
        values: (K, C) flattened primvar values (indices already applied).
        interpolation: 'constant', 'uniform', 'vertex', 'varying' or 'faceVarying'.
        triangulation: the mesh's fan triangulation.
        face_vertex_indices: (I,) int point index of each face-vertex corner.

    Returns:
        (T, 3, C) values, or None when `values` is too short for its interpolation (the caller
        warns and falls back).
    """
    values = np.asarray(values)
    corners = triangulation.corners
    if interpolation == UsdGeom.Tokens.constant:
        if len(values) < 1:
            return None
        return np.broadcast_to(values[0], corners.shape + values.shape[1:]).copy()
    if interpolation == UsdGeom.Tokens.uniform:
        lookup = np.broadcast_to(triangulation.face_ids[:, None], corners.shape)
    elif interpolation in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying):
        lookup = face_vertex_indices[corners]
    elif interpolation == UsdGeom.Tokens.faceVarying:
        lookup = corners
    else:
        return None
    if lookup.size and lookup.max() >= len(values):
        return None
    return values[lookup]


def read_primvar(prim: Usd.Prim, name: str, time: Usd.TimeCode) -> tuple[np.ndarray, str] | None:
    """Read a primvar with its indices applied.

    Args:
        prim: a gprim.
        name: primvar name without the 'primvars:' namespace, e.g. 'st'.
        time: time code to read.

    Returns:
        ((K, C) float32 values, interpolation token), or None if the primvar has no value.
    """
    primvar = UsdGeom.PrimvarsAPI(prim).GetPrimvar(name)
    if not primvar or not primvar.HasValue():
        return None
    values = primvar.ComputeFlattened(time)
    if values is None:
        return None
    array = np.asarray(values, np.float32)
    if not primvar.GetTypeName().isArray:
        array = array.reshape(1, -1)
    elif array.ndim == 1:
        array = array[:, None]
    return array, primvar.GetInterpolation()
