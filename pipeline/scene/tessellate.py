"""Every gprim as triangles in its own local space: polygon meshes and implicit surfaces.

Both produce a `Surface` whose triangles are counter-clockwise seen from their front side (a
`leftHanded` mesh is re-wound here), with per-corner shading normals and `st` coordinates.

Implicit gprims (Sphere, Cube, Cylinder, Cylinder_1, Cone, Capsule, Capsule_1, Plane) follow the
26.11 UsdGeom schema: sizes from their attributes, spine along `axis`, centred at the origin.
Round surfaces are surfaces of revolution about the spine, tessellated with `NUM_SEGMENTS` around
it and `NUM_RINGS` from pole to pole (sphere), with exact analytic normals so that shading is
smooth; flat parts (caps, cube faces, plane) get flat normals. Their uv: u = angle / 2 pi around
the spine, v = arc length along the profile normalised to [0, 1]; cube faces and the plane map
[0, 1]^2 per face. Their `orientation` is ignored: they are closed (or flat) analytic shapes whose
front side is the outside (or +axis).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pxr import Usd, UsdGeom

from pipeline.errors import warn
from pipeline.scene.primvars import Triangulation, expand, read_primvar, triangulate

NUM_SEGMENTS = 64
NUM_RINGS = 32

# Cyclic permutations (determinant +1) taking a shape built along Z to its `axis`.
_AXIS_PERMUTATION = {"X": [2, 0, 1], "Y": [1, 2, 0], "Z": [0, 1, 2]}


@dataclass(frozen=True)
class Surface:
    """One gprim's triangles in its local space.

    Attributes:
        positions: (T, 3, 3) float32 corner positions; counter-clockwise seen from the front.
        normals: (T, 3, 3) float32 unit shading normals per corner (zero where none could be
            computed; the caller falls back to the face normal).
        uvs: (T, 3, 2) float32 `st` per corner (zeros where the gprim has none).
        face_ids: (T,) int64 authored face of each triangle (indexes GeomSubsets; 0 for implicit
            gprims).
        num_faces: number of authored faces (1 for implicit gprims).
    """

    positions: np.ndarray
    normals: np.ndarray
    uvs: np.ndarray
    face_ids: np.ndarray
    num_faces: int = 1

    @property
    def num_triangles(self) -> int:
        return int(self.positions.shape[0])


def _normalized(vectors: np.ndarray) -> np.ndarray:
    """Unit vectors along the last axis; zero (not NaN) where the input is zero or non-finite."""
    vectors = np.where(np.isfinite(vectors), vectors, 0.0)
    length = np.linalg.norm(vectors, axis=-1, keepdims=True)
    return np.divide(vectors, length, out=np.zeros_like(vectors), where=length > 0)


# ---------------------------------------------------------------------------------------------
# Polygon meshes


def _accumulate(ids: np.ndarray, weights: np.ndarray, num_bins: int) -> np.ndarray:
    """Sum (N, 3) `weights` into `num_bins` bins by (N,) `ids` -> (num_bins, 3) float64."""
    return np.stack([np.bincount(ids, weights=weights[:, c], minlength=num_bins) for c in range(3)], axis=-1)


def _computed_normals(
    positions: np.ndarray,
    triangulation: Triangulation,
    counts: np.ndarray,
    indices: np.ndarray,
    num_points: int,
    smooth: bool,
) -> np.ndarray:
    """Area-weighted normals: smooth (per point) or flat (per authored face).

    A face's normal is the sum of its fan triangles' cross products (|cross| = 2 area, so the
    sum weights by area and handles non-planar faces); a point's smooth normal is the sum of the
    normals of the faces around it, each counted once.

    Args:
        positions: (T, 3, 3) triangle corner positions.
        triangulation: the (already re-wound) fan triangulation behind `positions`.
        counts: (F,) faceVertexCounts. indices: (I,) faceVertexIndices.
        num_points: number of mesh points. smooth: per-point normals, else per face.

    Returns:
        (T, 3, 3) float32 unit normals per corner (zero where undefined).
    """
    p = positions.astype(np.float64)
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    cross = np.where(np.isfinite(cross), cross, 0.0)
    per_face = _accumulate(triangulation.face_ids, cross, counts.size)
    if smooth:
        face_of_corner = np.repeat(np.arange(counts.size), counts)
        per_point = _accumulate(indices, per_face[face_of_corner], num_points)
        normals = per_point[indices[triangulation.corners]]
    else:
        normals = np.repeat(per_face[triangulation.face_ids][:, None], 3, axis=1)
    return _normalized(normals).astype(np.float32)


def corner_values(
    prim: Usd.Prim,
    name: str,
    values_and_interpolation,
    triangulation: Triangulation,
    face_vertex_indices: np.ndarray,
    warnings: list[str],
) -> np.ndarray | None:
    """Expand a read primvar per corner, warning when its size does not fit its interpolation."""
    if values_and_interpolation is None:
        return None
    values, interpolation = values_and_interpolation
    expanded = expand(values, interpolation, triangulation, face_vertex_indices)
    if expanded is None:
        warn(
            f"mesh {prim.GetPath()}: {name} has {len(values)} values, too few for "
            f"'{interpolation}' interpolation; ignored",
            warnings,
        )
    return expanded


def _authored_normals(mesh: UsdGeom.Mesh, time: Usd.TimeCode):
    """(values (K, 3), interpolation) of `primvars:normals`, else of `normals`, else None."""
    primvar = read_primvar(mesh.GetPrim(), "normals", time)
    if primvar is not None:
        return primvar
    normals = mesh.GetNormalsAttr().Get(time)
    if normals is None or len(normals) == 0:
        return None
    return np.asarray(normals, np.float32).reshape(-1, 3), mesh.GetNormalsInterpolation()


def uv_primvar(prim: Usd.Prim, time: Usd.TimeCode):
    """(values (K, 2), interpolation) of `st`, else of the first texCoord2f primvar, else None."""
    uv = read_primvar(prim, "st", time)
    if uv is not None:
        return uv
    for primvar in UsdGeom.PrimvarsAPI(prim).GetPrimvarsWithValues():
        if primvar.GetTypeName().role == "TextureCoordinate" and primvar.GetTypeName().isArray:
            return read_primvar(prim, primvar.GetPrimvarName(), time)
    return None


def mesh_topology(mesh: UsdGeom.Mesh, time: Usd.TimeCode, warnings: list[str]):
    """(points (V, 3) float32, counts (F,), indices (I,)) of a mesh, or None (after a warning when
    the topology is invalid) for an empty or invalid mesh."""
    path = mesh.GetPath()
    points = np.asarray(mesh.GetPointsAttr().Get(time) or [], np.float32).reshape(-1, 3)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(time) or [], np.int64)
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(time) or [], np.int64)
    if counts.size == 0 or (indices.size == 0 and not counts.any()):  # no faces, or only empty ones
        return None
    if counts.sum() != indices.size or (counts < 0).any() or indices.min() < 0 or indices.max() >= len(points):
        warn(
            f"mesh {path}: faceVertexCounts/faceVertexIndices do not match its {len(points)} points; skipped", warnings
        )
        return None
    if len(mesh.GetHoleIndicesAttr().Get(time) or []):
        warn(f"mesh {path}: holeIndices are not supported; hole faces are rendered", warnings)
    return points, counts, indices


def mesh_surface(mesh: UsdGeom.Mesh, time: Usd.TimeCode, warnings: list[str]) -> Surface | None:
    """Fan-triangulate a UsdGeom.Mesh (its control cage, for a subdivision surface) with its
    normals and `st`.

    Normals: `primvars:normals` if authored, else the `normals` attribute, else area-weighted
    smooth normals (flat per face when `subdivisionScheme` is 'none'). `holeIndices` are ignored
    (with a warning): hole faces are rendered. Subdivision surfaces are refined by
    `subdivided_surface`; this is their cage, used when the triangle budget allows no level.

    Args:
        mesh: the mesh. time: time code to read. warnings: sink for one-line warnings.

    Returns:
        The surface, or None (after a warning) when the mesh is empty or its topology invalid.
    """
    topology = mesh_topology(mesh, time, warnings)
    if topology is None:
        return None
    points, counts, indices = topology
    triangulation = triangulate(counts)
    if mesh.GetOrientationAttr().Get(time) == UsdGeom.Tokens.leftHanded:
        triangulation = Triangulation(triangulation.corners[:, [0, 2, 1]], triangulation.face_ids)
    point_ids = indices[triangulation.corners]
    positions = points[point_ids]

    prim = mesh.GetPrim()
    normals = corner_values(prim, "normals", _authored_normals(mesh, time), triangulation, indices, warnings)
    if normals is None:
        smooth = mesh.GetSubdivisionSchemeAttr().Get(time) != UsdGeom.Tokens.none
        normals = _computed_normals(positions, triangulation, counts, indices, len(points), smooth)
    uvs = corner_values(prim, "st", uv_primvar(prim, time), triangulation, indices, warnings)
    if uvs is None or uvs.shape[-1] != 2:
        uvs = np.zeros(positions.shape[:2] + (2,), np.float32)
    return Surface(
        positions=positions,
        normals=_normalized(normals).astype(np.float32),
        uvs=uvs.astype(np.float32),
        face_ids=triangulation.face_ids,
        num_faces=int(counts.size),
    )


# ---------------------------------------------------------------------------------------------
# Surfaces of revolution about +Z (sphere, cylinder, cone, capsule)


@dataclass(frozen=True)
class _Profile:
    """A polyline in the (radius, z) half-plane, with the outward normal at each vertex.

    Ordered so that revolving it counter-clockwise about +Z gives outward-facing triangles:
    upward along a side, outward along a bottom cap, inward along a top cap.

    Attributes:
        radius, z: (P,) float64 vertex coordinates (radius exactly 0 on the axis).
        normal: (P, 2) float64 unit (radial, z) outward normal.
    """

    radius: np.ndarray
    z: np.ndarray
    normal: np.ndarray


def _arc(center_z: float, radius: float, theta_start: float, theta_end: float, num_points: int) -> _Profile:
    """Circular arc of a sphere's profile, elevation angle theta from -pi/2 (bottom pole) up."""
    theta = np.linspace(theta_start, theta_end, num_points)
    normal = np.stack((np.cos(theta), np.sin(theta)), axis=-1)
    normal[np.isclose(np.abs(theta), np.pi / 2), 0] = 0.0  # exact poles, on the axis
    return _Profile(radius * normal[:, 0], center_z + radius * normal[:, 1], normal)


def _disk(z: float, radius: float, facing_up: bool) -> _Profile:
    """A flat cap at height z: bottom caps run outward, top caps inward."""
    radii = np.array([radius, 0.0]) if facing_up else np.array([0.0, radius])
    normal = np.tile([0.0, 1.0 if facing_up else -1.0], (2, 1))
    return _Profile(radii, np.full(2, z), normal)


def _frustum_side(radius_bottom: float, radius_top: float, height: float) -> _Profile:
    """The slanted side of a cylinder or cone from z = -height/2 up to +height/2."""
    normal = np.array([height, radius_bottom - radius_top], np.float64)
    normal /= np.linalg.norm(normal)
    return _Profile(np.array([radius_bottom, radius_top]), np.array([-height, height]) / 2, np.tile(normal, (2, 1)))


def _revolve(profiles: list[_Profile], axis: str) -> Surface:
    """Revolve profiles about +Z with NUM_SEGMENTS segments, then turn +Z onto `axis`."""
    phi = np.linspace(0.0, 2.0 * np.pi, NUM_SEGMENTS + 1)
    cos, sin = np.cos(phi), np.sin(phi)
    cos[-1], sin[-1] = 1.0, 0.0  # the seam closes exactly
    lengths = [np.hypot(np.diff(p.radius), np.diff(p.z)) for p in profiles]
    total_length = sum(float(s.sum()) for s in lengths)
    offset = 0.0
    positions, normals, uvs = [], [], []
    for profile, segment_lengths in zip(profiles, lengths, strict=True):
        v = (offset + np.concatenate(([0.0], np.cumsum(segment_lengths)))) / total_length
        offset += float(segment_lengths.sum())
        # (P, S+1, C) grids of vertex attributes.
        r, nr = profile.radius[:, None], profile.normal[:, 0, None]
        grid_p = np.stack(np.broadcast_arrays(r * cos, r * sin, profile.z[:, None]), axis=-1)
        grid_n = np.stack(np.broadcast_arrays(nr * cos, nr * sin, profile.normal[:, 1, None]), -1)
        grid_uv = np.stack(np.broadcast_arrays(phi[None, :] / (2 * np.pi), v[:, None]), axis=-1)
        idx = np.arange(grid_p.shape[0] * grid_p.shape[1]).reshape(grid_p.shape[:2])
        a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
        # A quad (a, b, c, d) loses the triangle whose edge collapses onto the axis.
        keep_abc = np.broadcast_to(profile.radius[:-1, None] > 0, a.shape)
        keep_acd = np.broadcast_to(profile.radius[1:, None] > 0, a.shape)
        corners = np.concatenate((np.stack((a, b, c), -1)[keep_abc], np.stack((a, c, d), -1)[keep_acd]))
        positions.append(grid_p.reshape(-1, 3)[corners])
        normals.append(grid_n.reshape(-1, 3)[corners])
        uvs.append(grid_uv.reshape(-1, 2)[corners])
    permutation = _AXIS_PERMUTATION[axis]
    positions = np.concatenate(positions)[..., permutation]
    normals = np.concatenate(normals)[..., permutation]
    return _surface(positions, normals, np.concatenate(uvs))


def _surface(positions: np.ndarray, normals: np.ndarray, uvs: np.ndarray) -> Surface:
    return Surface(
        positions=positions.astype(np.float32),
        normals=normals.astype(np.float32),
        uvs=uvs.astype(np.float32),
        face_ids=np.zeros(len(positions), np.int64),
    )


def _capsule(radius_bottom: float, radius_top: float, height: float, axis: str) -> Surface:
    """Two spheres centred at -/+ height/2 joined by the cone tangent to both (C1 continuous)."""
    # Elevation of the side's normal: sin(alpha) = (r_bottom - r_top) / distance of the centres.
    alpha = float(np.arcsin(np.clip((radius_bottom - radius_top) / max(height, 1e-30), -1, 1)))
    num = NUM_RINGS // 2 + 1
    bottom = _arc(-height / 2, radius_bottom, -np.pi / 2, alpha, num)
    top = _arc(height / 2, radius_top, alpha, np.pi / 2, num)
    return _revolve(
        [
            _Profile(
                np.concatenate((bottom.radius, top.radius)),
                np.concatenate((bottom.z, top.z)),
                np.concatenate((bottom.normal, top.normal)),
            )
        ],
        axis,
    )


def _frustum(radius_bottom: float, radius_top: float, height: float, axis: str) -> Surface:
    """A capped cylinder (equal radii), cone (top radius 0) or truncated cone."""
    profiles = [_frustum_side(radius_bottom, radius_top, height)]
    if radius_bottom > 0:
        profiles.insert(0, _disk(-height / 2, radius_bottom, facing_up=False))
    if radius_top > 0:
        profiles.append(_disk(height / 2, radius_top, facing_up=True))
    return _revolve(profiles, axis)


# ---------------------------------------------------------------------------------------------
# Flat implicit gprims


def _quads(centers: np.ndarray, half_u: np.ndarray, half_v: np.ndarray, normals: np.ndarray) -> Surface:
    """Planar quads centre +- half_u +- half_v, each as 2 triangles with flat normals.

    Args:
        centers, half_u, half_v, normals: (Q, 3); half_u x half_v must point along the normal.
    """
    signs = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], np.float64)  # (4, 2), uv = (s+1)/2
    corners = (
        centers[:, None] + signs[None, :, 0, None] * half_u[:, None] + signs[None, :, 1, None] * half_v[:, None]
    )  # (Q, 4, 3)
    triangles = np.array([[0, 1, 2], [0, 2, 3]])
    positions = corners[:, triangles].reshape(-1, 3, 3)
    uvs = np.broadcast_to(((signs + 1) / 2)[triangles], (len(centers), 2, 3, 2)).reshape(-1, 3, 2)
    face_normals = np.repeat(normals, 6, axis=0).reshape(-1, 3, 3)
    return _surface(positions, face_normals, uvs)


def _cube(size: float) -> Surface:
    """Axis-aligned cube of edge `size` centred at the origin; 12 triangles."""
    normals = np.concatenate((np.eye(3), -np.eye(3)))
    tangents = np.roll(normals, 1, axis=1)  # any unit vector perpendicular to the normal
    bitangents = np.cross(normals, tangents)
    half = size / 2
    return _quads(normals * half, tangents * half, bitangents * half, normals)


def _plane(width: float, length: float, axis: str) -> Surface:
    """Plane through the origin facing +axis: width along x (z when axis is X), length along
    y (z when axis is Y)."""
    eye = np.eye(3)
    normal = eye["XYZ".index(axis)]
    along_width = eye[2] if axis == "X" else eye[0]
    along_length = eye[2] if axis == "Y" else eye[1]
    if np.dot(np.cross(along_width, along_length), normal) < 0:
        along_length = -along_length  # keep the winding counter-clockwise seen from +axis
    return _quads(np.zeros((1, 3)), along_width[None] * width / 2, along_length[None] * length / 2, normal[None])


# ---------------------------------------------------------------------------------------------
# Dispatch


def _get(attribute: Usd.Attribute, time: Usd.TimeCode) -> float:
    return float(attribute.Get(time))


def _axis(schema, time: Usd.TimeCode) -> str:
    return str(schema.GetAxisAttr().Get(time))


def _sphere(prim, time):
    radius = _get(UsdGeom.Sphere(prim).GetRadiusAttr(), time)
    return _revolve([_arc(0.0, radius, -np.pi / 2, np.pi / 2, NUM_RINGS + 1)], "Z")


def _cylinder(prim, time):
    g = UsdGeom.Cylinder(prim)
    radius = _get(g.GetRadiusAttr(), time)
    return _frustum(radius, radius, _get(g.GetHeightAttr(), time), _axis(g, time))


def _cylinder_1(prim, time):
    g = UsdGeom.Cylinder_1(prim)
    return _frustum(
        _get(g.GetRadiusBottomAttr(), time),
        _get(g.GetRadiusTopAttr(), time),
        _get(g.GetHeightAttr(), time),
        _axis(g, time),
    )


def _cone(prim, time):
    g = UsdGeom.Cone(prim)
    return _frustum(_get(g.GetRadiusAttr(), time), 0.0, _get(g.GetHeightAttr(), time), _axis(g, time))


def _capsule_0(prim, time):
    g = UsdGeom.Capsule(prim)
    radius = _get(g.GetRadiusAttr(), time)
    return _capsule(radius, radius, _get(g.GetHeightAttr(), time), _axis(g, time))


def _capsule_1(prim, time):
    g = UsdGeom.Capsule_1(prim)
    return _capsule(
        _get(g.GetRadiusBottomAttr(), time),
        _get(g.GetRadiusTopAttr(), time),
        _get(g.GetHeightAttr(), time),
        _axis(g, time),
    )


def _cube_prim(prim, time):
    return _cube(_get(UsdGeom.Cube(prim).GetSizeAttr(), time))


def _plane_prim(prim, time):
    g = UsdGeom.Plane(prim)
    return _plane(_get(g.GetWidthAttr(), time), _get(g.GetLengthAttr(), time), _axis(g, time))


_IMPLICIT = (
    (UsdGeom.Sphere, _sphere),
    (UsdGeom.Cube, _cube_prim),
    (UsdGeom.Cylinder, _cylinder),
    (UsdGeom.Cylinder_1, _cylinder_1),
    (UsdGeom.Cone, _cone),
    (UsdGeom.Capsule, _capsule_0),
    (UsdGeom.Capsule_1, _capsule_1),
    (UsdGeom.Plane, _plane_prim),
)


def is_implicit(prim: Usd.Prim) -> bool:
    """Whether `prim` is one of the implicit gprims `implicit_surface` tessellates."""
    return any(prim.IsA(schema) for schema, _ in _IMPLICIT)


def implicit_surface(prim: Usd.Prim, time: Usd.TimeCode) -> Surface:
    """Tessellate an implicit gprim (see the module docstring for resolution and uvs).

    Args:
        prim: a Sphere, Cube, Cylinder(_1), Cone, Capsule(_1) or Plane prim.
        time: time code to read its size attributes at.
    """
    for schema, build in _IMPLICIT:
        if prim.IsA(schema):
            return build(prim, time)
    raise TypeError(f"{prim.GetPath()} is not an implicit gprim")
