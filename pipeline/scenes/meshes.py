"""Polygon meshes for the bundled scenes, generated with numpy (no per-vertex Python loops).

Every mesh is right-handed: a face's corners run counter-clockwise seen from the side its normal
points to, i.e. normal ~ (p1 - p0) x (p2 - p0). Normals and st are per point ('vertex'
interpolation); hard edges are made by giving each flat face its own points (boxes) or by merging
separately revolved smooth bands.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MeshData:
    """A polygon mesh in its own (local) frame.

    Attributes:
        points: (P, 3) float32 positions.
        face_vertex_counts: (F,) int32 corners per face (3 or 4 here).
        face_vertex_indices: (sum(face_vertex_counts),) int32 point indices, faces concatenated.
        normals: (P, 3) float32 unit normals per point, or None (renderers use face normals).
        st: (P, 2) float32 texture coordinates per point, or None.
    """

    points: np.ndarray
    face_vertex_counts: np.ndarray
    face_vertex_indices: np.ndarray
    normals: np.ndarray | None = None
    st: np.ndarray | None = None

    @property
    def num_triangles(self) -> int:
        """Triangles after fan triangulation: sum over faces of (corners - 2)."""
        return int(np.sum(self.face_vertex_counts - 2))


def _mesh(points, counts, indices, normals=None, st=None) -> MeshData:
    return MeshData(
        points=np.asarray(points, np.float32),
        face_vertex_counts=np.asarray(counts, np.int32),
        face_vertex_indices=np.asarray(indices, np.int32).ravel(),
        normals=None if normals is None else np.asarray(normals, np.float32),
        st=None if st is None else np.asarray(st, np.float32),
    )


def _normalized(vectors: np.ndarray) -> np.ndarray:
    return vectors / np.linalg.norm(vectors, axis=-1, keepdims=True)


def polygons(corners: np.ndarray) -> MeshData:
    """Independent planar polygons with the same corner count, without normals or st.

    Args:
        corners: (F, C, 3) corner positions, each polygon wound as it should face.
    """
    num_faces, num_corners = corners.shape[:2]
    return _mesh(corners.reshape(-1, 3), np.full(num_faces, num_corners), np.arange(num_faces * num_corners))


def newell_normals(corners: np.ndarray) -> np.ndarray:
    """Unit normals of planar-ish polygons by Newell's method, following the winding.

    Args:
        corners: (F, C, 3) polygon corners.

    Returns:
        (F, 3) float64 unit normals, (p1 - p0) x (p2 - p0) direction for a convex polygon.
    """
    corners = np.asarray(corners, np.float64)
    following = np.roll(corners, -1, axis=1)
    return _normalized(np.cross(corners, following).sum(axis=1))


def orient_polygons(corners: np.ndarray, facing: np.ndarray) -> np.ndarray:
    """Reverse the winding of the polygons whose normal points away from `facing`.

    Args:
        corners: (F, C, 3) polygon corners in any winding.
        facing: (F, 3) the direction each polygon's front side should face.

    Returns:
        (F, C, 3) corners, wound so that newell_normals(...) . facing > 0.
    """
    flip = np.einsum("fi,fi->f", newell_normals(corners), facing) < 0
    return np.where(flip[:, None, None], corners[:, ::-1], corners)


def plane(size_x: float, size_z: float, st_repeat: float = 1.0) -> MeshData:
    """A quad in the XZ plane centred at the origin, facing +Y; +s along +x, +t along -z.

    Args:
        size_x, size_z: extents along x and z.
        st_repeat: st runs from 0 to this value along each edge (texture repeats).
    """
    half_x, half_z = 0.5 * size_x, 0.5 * size_z
    points = [(-half_x, 0, half_z), (half_x, 0, half_z), (half_x, 0, -half_z), (-half_x, 0, -half_z)]
    st = np.array([[0, 0], [1, 0], [1, 1], [0, 1]]) * st_repeat
    return _mesh(points, [4], [0, 1, 2, 3], normals=np.tile([0.0, 1.0, 0.0], (4, 1)), st=st)


def box(size: tuple[float, float, float], center: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> MeshData:
    """An axis-aligned box: 6 quads with their own 4 points each (flat normals), st per face in [0, 1]^2.

    Args:
        size: (3,) edge lengths along x, y, z.
        center: (3,) centre position.
    """
    half = 0.5 * np.asarray(size, np.float64)
    eye = np.eye(3)
    # Per face: outward normal n and in-plane axes u, v with u x v = n, so (0,0),(1,0),(1,1),(0,1)
    # in (u, v) runs counter-clockwise seen from outside.
    normal = np.concatenate([eye, -eye])  # +x +y +z -x -y -z
    u_axis = eye[[1, 2, 0, 2, 0, 1]]
    v_axis = np.cross(normal, u_axis)
    unit_square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float64)  # (4, 2) st per corner
    offsets = (
        normal[:, None]
        + (2 * unit_square[None, :, :1] - 1) * u_axis[:, None]
        + (2 * unit_square[None, :, 1:] - 1) * v_axis[:, None]
    )  # (6, 4, 3)
    points = np.asarray(center, np.float64) + offsets * half
    return _mesh(
        points.reshape(-1, 3),
        np.full(6, 4),
        np.arange(24),
        normals=np.repeat(normal, 4, axis=0),
        st=np.tile(unit_square, (6, 1)),
    )


def revolve(
    profile: np.ndarray,
    num_segments: int,
    *,
    angle_range: tuple[float, float] = (0.0, 2 * np.pi),
    closed_profile: bool = False,
) -> MeshData:
    """A smooth surface of revolution about the local +Y axis.

    The profile is a polyline in the (radius, height) half-plane; a point (r, h) at angle theta
    lands at (r sin theta, h, r cos theta). The outside of the surface is on the RIGHT of the
    profile's direction of travel (a profile going up at r > 0 faces outwards), and the normals are
    the profile's smooth (central-difference) normals swept around, so sample sharp corners as
    separate `revolve` calls and `merge` them. Profile points on the axis (r = 0) become poles with
    triangles instead of degenerate quads.

    Args:
        profile: (K, 2) radius, height samples, K >= 2.
        num_segments: S, segments around the axis.
        angle_range: (start, end) angles in radians; the full turn closes the surface.
        closed_profile: join the last profile point back to the first (e.g. a torus tube).

    Returns:
        MeshData with (K [+1], S + 1) points (the seam duplicated so st has no wrap), st =
        (angle fraction, profile arc-length fraction).
    """
    profile = np.array(profile, np.float64)  # a copy: poles are snapped to r = 0 below
    if closed_profile:
        profile_for_tangent = np.concatenate([profile[-1:], profile, profile[:1]])
        tangent = profile_for_tangent[2:] - profile_for_tangent[:-2]
        profile, tangent = np.concatenate([profile, profile[:1]]), np.concatenate([tangent, tangent[:1]])
    else:
        tangent = np.gradient(profile, axis=0)
    normal_rh = _normalized(np.stack([tangent[:, 1], -tangent[:, 0]], axis=-1))  # (K, 2) right of travel
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(profile, axis=0), axis=-1))])
    on_axis = profile[:, 0] <= 1e-9 * np.abs(profile).max()  # e.g. sin(pi) * r is 1e-16, not 0
    profile[on_axis, 0] = 0.0

    num_rows, num_columns = len(profile), num_segments + 1
    theta = np.linspace(angle_range[0], angle_range[1], num_columns)
    sin, cos = np.sin(theta)[None, :], np.cos(theta)[None, :]  # (1, S + 1)
    rows = (num_rows, num_columns)
    points = np.stack([profile[:, :1] * sin, np.broadcast_to(profile[:, 1:], rows), profile[:, :1] * cos], -1)
    normals = np.stack([normal_rh[:, :1] * sin, np.broadcast_to(normal_rh[:, 1:], rows), normal_rh[:, :1] * cos], -1)
    st = np.stack(np.broadcast_arrays(np.linspace(0.0, 1.0, num_columns)[None, :], (arc / arc[-1])[:, None]), -1)

    # Quad (k, j) -> corners (k, j), (k, j+1), (k+1, j+1), (k+1, j): first edge around the axis, then
    # along the profile, whose cross product points to the right of the profile's travel.
    k, j = np.meshgrid(np.arange(num_rows - 1), np.arange(num_segments), indexing="ij")
    quads = np.stack(
        [k * num_columns + j, k * num_columns + j + 1, (k + 1) * num_columns + j + 1, (k + 1) * num_columns + j], -1
    )  # (K-1, S, 4)
    faces, counts = [], []
    for row in range(num_rows - 1):
        # A pole row collapses one edge of its quads: drop the duplicate corner.
        if on_axis[row]:
            row_faces = quads[row][:, [0, 2, 3]]
        elif on_axis[row + 1]:
            row_faces = quads[row][:, [0, 1, 2]]
        else:
            row_faces = quads[row]
        faces.append(row_faces.ravel())
        counts.append(np.full(num_segments, row_faces.shape[1]))
    return _mesh(
        points.reshape(-1, 3),
        np.concatenate(counts),
        np.concatenate(faces),
        normals=normals.reshape(-1, 3),
        st=st.reshape(-1, 2),
    )


def merge(meshes: list[MeshData]) -> MeshData:
    """Concatenate meshes into one (normals/st kept only if every part has them)."""
    offsets = np.cumsum([0] + [len(mesh.points) for mesh in meshes[:-1]])
    has_normals = all(mesh.normals is not None for mesh in meshes)
    has_st = all(mesh.st is not None for mesh in meshes)
    return _mesh(
        np.concatenate([mesh.points for mesh in meshes]),
        np.concatenate([mesh.face_vertex_counts for mesh in meshes]),
        np.concatenate([mesh.face_vertex_indices + offset for mesh, offset in zip(meshes, offsets, strict=True)]),
        normals=np.concatenate([mesh.normals for mesh in meshes]) if has_normals else None,
        st=np.concatenate([mesh.st for mesh in meshes]) if has_st else None,
    )


def transformed(mesh: MeshData, parent_from_local: np.ndarray) -> MeshData:
    """The mesh moved by a (4, 4) column-vector affine matrix; normals by the inverse transpose.

    A transform with negative determinant would turn the faces inside out; it is rejected.
    """
    linear, translation = parent_from_local[:3, :3], parent_from_local[:3, 3]
    if np.linalg.det(linear) <= 0:
        raise ValueError(f"transformed: matrix must preserve orientation, det = {np.linalg.det(linear)}")
    normals = None
    if mesh.normals is not None:
        normals = _normalized(mesh.normals @ np.linalg.inv(linear))  # n' = inv(A).T n, row-vector form
    return _mesh(
        mesh.points @ linear.T + translation,
        mesh.face_vertex_counts,
        mesh.face_vertex_indices,
        normals=normals,
        st=mesh.st,
    )


def uv_sphere(radius: float, num_segments: int, num_rings: int) -> MeshData:
    """A sphere centred at the origin, poles on the Y axis, triangles at the poles."""
    polar = np.linspace(0.0, np.pi, num_rings + 1)
    return revolve(np.stack([radius * np.sin(polar), -radius * np.cos(polar)], -1), num_segments)


def torus(major_radius: float, minor_radius: float, num_segments: int, num_tube_segments: int) -> MeshData:
    """A torus around the Y axis, centred at the origin."""
    angle = np.linspace(0.0, 2 * np.pi, num_tube_segments, endpoint=False)
    tube = np.stack([major_radius + minor_radius * np.cos(angle), minor_radius * np.sin(angle)], -1)
    return revolve(tube, num_segments, closed_profile=True)
