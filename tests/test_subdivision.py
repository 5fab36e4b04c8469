"""Subdivision surfaces: limit-surface properties of the vectorised Catmull-Clark and Loop
refinement (B-spline patches, the cube's limit shape, stationarity of the limit stencils at every
valence, boundaries, creases and corners), the screen-space level choice and the USD reading."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom

from pipeline.benchmarks.subdivision import CUBE_FACES, CUBE_POINTS, cube_cage_stage, silhouette_error
from pipeline.scene import dicing
from pipeline.scene import geometry as geometry_module
from pipeline.scene.geometry import read_geometry
from pipeline.scene.load import read_scene
from pipeline.scene.materials import MaterialLibrary
from pipeline.scene.subdivide import limit_surface, make_cage, refined_triangles, step, triangle_count
from pipeline.scene.types import Camera

DEFAULT = Usd.TimeCode.Default()


def _cube(**kwargs):
    return make_cage(CUBE_POINTS, [4] * 6, CUBE_FACES.ravel(), **kwargs)


def _cube_edges() -> np.ndarray:
    edges = {tuple(sorted((f[k], f[(k + 1) % 4]))) for f in CUBE_FACES.tolist() for k in range(4)}
    return np.array(sorted(edges))


def _icosahedron():
    t = (1 + 5**0.5) / 2
    points = np.array(
        [
            [-1, t, 0],
            [1, t, 0],
            [-1, -t, 0],
            [1, -t, 0],
            [0, -1, t],
            [0, 1, t],
            [0, -1, -t],
            [0, 1, -t],
            [t, 0, -1],
            [t, 0, 1],
            [-t, 0, -1],
            [-t, 0, 1],
        ],
        np.float64,
    )
    faces = [
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ]
    return make_cage(points / np.linalg.norm(points[0]), [3] * 20, np.array(faces).ravel())


def _grid(size: int, heights: np.ndarray, triangles: bool = False, **kwargs):
    """A size x size grid of points (i, j, height) with quads (or two triangles per quad)
    counter-clockwise seen from +Z."""
    i, j = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
    points = np.stack((i, j, heights), axis=-1).reshape(-1, 3).astype(np.float64)
    v = np.arange(size * size).reshape(size, size)
    a, b, c, d = v[:-1, :-1], v[1:, :-1], v[1:, 1:], v[:-1, 1:]
    if triangles:
        faces = np.concatenate((np.stack((a, b, c), -1).reshape(-1, 3), np.stack((a, c, d), -1).reshape(-1, 3)))
    else:
        faces = np.stack((a, b, c, d), -1).reshape(-1, 4)
    return make_cage(points, np.full(len(faces), faces.shape[1]), faces.ravel(), **kwargs)


def _bspline_basis(t: np.ndarray) -> np.ndarray:
    """(N, 4) uniform cubic B-spline basis at t in [0, 1)."""
    return np.stack(((1 - t) ** 3, 3 * t**3 - 6 * t**2 + 4, -3 * t**3 + 3 * t**2 + 3 * t + 1, t**3), -1) / 6


def _bspline_derivative(t: np.ndarray) -> np.ndarray:
    return np.stack((-3 * (1 - t) ** 2, 9 * t**2 - 12 * t, -9 * t**2 + 6 * t + 3, 3 * t**2), -1) / 6


def _bspline_surface(control: np.ndarray, u: np.ndarray, v: np.ndarray):
    """Uniform bicubic B-spline of a (S, S) control grid at parameters (u, v) in control-index
    units: (value, d/du, d/dv), each (N,)."""
    ku, kv = np.floor(u).astype(int), np.floor(v).astype(int)
    bu, bv = _bspline_basis(u - ku), _bspline_basis(v - kv)
    du, dv = _bspline_derivative(u - ku), _bspline_derivative(v - kv)
    rows = ku[:, None] - 1 + np.arange(4)
    cols = kv[:, None] - 1 + np.arange(4)
    patch = control[rows[:, :, None], cols[:, None, :]]  # (N, 4, 4)
    value = np.einsum("ni,nij,nj->n", bu, patch, bv)
    return value, np.einsum("ni,nij,nj->n", du, patch, bv), np.einsum("ni,nij,nj->n", bu, patch, dv)


def _vertices(result) -> tuple[np.ndarray, np.ndarray]:
    """Unique (positions, normals) of the triangles' corners."""
    positions = result["positions"].reshape(-1, 3)
    normals = result["normals"].reshape(-1, 3)
    _, first = np.unique(np.round(positions, 9), axis=0, return_index=True)
    return positions[first], normals[first]


# ---------------------------------------------------------------------------------------------
# Limit-surface properties


@pytest.mark.parametrize("levels", [1, 3])
def test_regular_patch_is_the_bicubic_bspline(levels):
    """Interior of a regular quad grid: limit positions and normals equal the uniform bicubic
    B-spline of the control points evaluated independently (x, y reproduce u, v exactly)."""
    rng = np.random.default_rng(1)
    heights = rng.uniform(-0.5, 0.5, (7, 7))
    positions, normals = _vertices(refined_triangles(_grid(7, heights), "catmullClark", levels))
    inside = np.all((positions[:, :2] >= 2) & (positions[:, :2] <= 4), axis=1)
    assert inside.sum() == (2 * 2**levels + 1) ** 2
    u, v = positions[inside, 0], positions[inside, 1]
    value, d_du, d_dv = _bspline_surface(heights, np.minimum(u, 4 - 1e-12), np.minimum(v, 4 - 1e-12))
    np.testing.assert_allclose(positions[inside, 2], value, atol=1e-12)
    expected_normal = np.stack((-d_du, -d_dv, np.ones_like(u)), -1)
    expected_normal /= np.linalg.norm(expected_normal, axis=-1, keepdims=True)
    np.testing.assert_allclose(normals[inside], expected_normal, atol=1e-6)


def test_boundary_curve_is_the_cubic_bspline_of_the_boundary():
    """Away from the corners, a boundary of the grid converges to the uniform cubic B-spline of
    its boundary control points (the boundary edges are sharp)."""
    rng = np.random.default_rng(2)
    heights = rng.uniform(-0.5, 0.5, (7, 7))
    positions, _ = _vertices(refined_triangles(_grid(7, heights), "catmullClark", 3))
    on_edge = (positions[:, 1] == 0) & (positions[:, 0] >= 2) & (positions[:, 0] <= 4)
    u = positions[on_edge, 0]
    k = np.minimum(np.floor(u).astype(int), 3)
    basis = _bspline_basis(u - k)
    expected = np.sum(basis * heights[k[:, None] - 1 + np.arange(4), 0], axis=-1)
    np.testing.assert_allclose(positions[on_edge, 2], expected, atol=1e-12)


@pytest.mark.parametrize("boundary, corner_moves", [("edgeAndCorner", False), ("edgeOnly", True)])
def test_boundary_corners(boundary, corner_moves):
    """'edgeAndCorner' keeps a grid's corner points; 'edgeOnly' rounds them off."""
    heights = np.zeros((4, 4))
    heights[0, 0] = 1.0
    positions, _ = _vertices(refined_triangles(_grid(4, heights, interpolate_boundary=boundary), "catmullClark", 2))
    at_corner = np.linalg.norm(positions - [0, 0, 1], axis=-1).min()
    assert (at_corner > 1e-3) == corner_moves


def test_cube_converges_to_its_known_limit_shape():
    """Catmull-Clark cube [-1, 1]^3: the corner's limit is (1/2, 1/2, 1/2) and the face centre's
    is 68/81 along its axis (both derived by hand from the rules); every limit point lies between
    those distances from the centre, and the shape has the cube's symmetries."""
    for levels in (1, 4):
        result = refined_triangles(_cube(), "catmullClark", levels)
        positions, normals = _vertices(result)
        radius = np.linalg.norm(positions, axis=-1)
        assert radius.min() == pytest.approx(68 / 81, abs=1e-12)
        assert radius.max() == pytest.approx(np.sqrt(3) / 2, abs=1e-12)
        assert np.abs(positions).max() == pytest.approx(68 / 81, abs=1e-12)
        corner = positions[np.argmax(radius)]
        np.testing.assert_allclose(np.abs(corner), 0.5, atol=1e-12)
        # Symmetric under every axis flip and permutation.
        key = np.sort(np.round(positions, 9), axis=0)
        for transform in (positions * [-1, 1, 1], positions[:, [1, 2, 0]], positions[:, [1, 0, 2]]):
            np.testing.assert_allclose(np.sort(np.round(transform, 9), axis=0), key, atol=1e-9)
        # Normals point outwards and agree with the faces' winding.
        assert np.all(np.sum(normals * positions, axis=-1) > 0)
        p = result["positions"]
        assert np.all(np.sum(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]) * p.mean(axis=1), axis=-1) > 0)


def test_icosahedron_loop_surface_is_nearly_a_sphere():
    """Loop on a unit icosahedron: the limit surface is round to within 1.6% in radius (measured
    1.47%, set by the valence-5 vertices), and its normals are nearly radial."""
    result = refined_triangles(_icosahedron(), "loop", 4)
    positions, normals = _vertices(result)
    radius = np.linalg.norm(positions, axis=-1)
    assert (radius.max() - radius.min()) / radius.mean() < 0.016
    cos_angle = np.sum(normals * positions / radius[:, None], axis=-1)
    assert cos_angle.min() > 0.995
    assert len(result["positions"]) == triangle_count(np.full(20, 3), "loop", 4) == 20 * 4**4


def _stationarity(cage, scheme: str, levels: int) -> float:
    """Largest move of the limit positions of the vertices of `levels` when computed one level later
    (vertex points come first in every level, so vertex k stays vertex k)."""
    for _ in range(levels):
        cage = step(cage, scheme)
    coarse, _ = limit_surface(cage, scheme)
    fine, _ = limit_surface(step(cage, scheme), scheme)
    return float(np.abs(fine[: len(coarse)] - coarse).max())


def _pentagon_prism():
    """A closed prism over a pentagon: valence-3 vertices, two pentagons (valence 5 after one level)."""
    angle = 2 * np.pi * np.arange(5) / 5
    ring = np.stack((np.cos(angle), np.sin(angle)), -1)
    points = np.concatenate((np.c_[ring, -np.ones(5)], np.c_[ring, np.ones(5)]))
    sides = [[k, (k + 1) % 5, 5 + (k + 1) % 5, 5 + k] for k in range(5)]
    faces = sides + [[4, 3, 2, 1, 0], [5, 6, 7, 8, 9]]
    return make_cage(points, [len(f) for f in faces], np.concatenate(faces))


@pytest.mark.parametrize(
    "name",
    [
        "cube",
        "pentagon prism",
        "sharp loop",
        "grid edgeOnly",
        "grid edgeAndCorner",
        "loop icosahedron",
        "loop grid",
        "corner",
    ],
)
def test_limit_stencils_are_stationary(name):
    """Limit positions computed at level L and at L + 1 agree at every valence (3, 4, 5, 6),
    on boundaries, infinitely sharp creases and corners: the stencils are the true limit."""
    heights = np.random.default_rng(3).uniform(-0.3, 0.3, (5, 5))
    cases = {
        "cube": (_cube(), "catmullClark"),
        "pentagon prism": (_pentagon_prism(), "catmullClark"),
        # A closed crease loop round one face (crease rule at its vertices; darts, one sharp edge
        # at a vertex, use the smooth mask as OpenSubdiv does and are not stationary).
        "sharp loop": (
            _cube(crease_edges=[[4, 6], [6, 7], [7, 5], [5, 4]], crease_sharpness=np.full(4, 10.0)),
            "catmullClark",
        ),
        "grid edgeOnly": (_grid(5, heights, interpolate_boundary="edgeOnly"), "catmullClark"),
        "grid edgeAndCorner": (_grid(5, heights), "catmullClark"),
        "loop icosahedron": (_icosahedron(), "loop"),
        "loop grid": (_grid(5, heights, triangles=True), "loop"),  # valences 4, 6 and boundaries
        "corner": (_cube(corner_indices=[7], corner_sharpness=[10.0]), "catmullClark"),
    }
    cage, scheme = cases[name]
    assert _stationarity(cage, scheme, 2) < 1e-12


def test_infinitely_sharp_cube_keeps_its_faces_and_hard_normals():
    """Every edge creased (sharpness >= 10 is infinite): the limit is the cube itself, and each
    corner's normal is its own face's (sectors stop at sharp edges)."""
    result = refined_triangles(_cube(crease_edges=_cube_edges(), crease_sharpness=np.full(12, 10.0)), "catmullClark", 3)
    np.testing.assert_allclose(np.abs(result["positions"]).max(axis=-1), 1.0, atol=1e-12)
    p = result["positions"]
    face_normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    face_normal /= np.linalg.norm(face_normal, axis=-1, keepdims=True)
    np.testing.assert_allclose(result["normals"], np.repeat(face_normal[:, None], 3, axis=1), atol=1e-12)


def test_semi_sharp_creases_lie_between_smooth_and_sharp():
    """Sharper creases keep more of the cube: the corners' distance from the centre grows with
    the sharpness, from the smooth limit's sqrt(3) / 2 to the cube's sqrt(3)."""
    corners = []
    for sharpness in (0.0, 0.5, 1.0, 2.0, 10.0):
        cage = _cube(crease_edges=_cube_edges(), crease_sharpness=np.full(12, sharpness))
        positions = refined_triangles(cage, "catmullClark", 4)["positions"]
        corners.append(float(np.linalg.norm(positions, axis=-1).max()))
    assert corners[0] == pytest.approx(np.sqrt(3) / 2, abs=1e-12)
    assert np.all(np.diff(corners) > 0)
    assert corners[-1] == pytest.approx(np.sqrt(3), abs=1e-12)


def test_corner_vertex_stays_put():
    result = refined_triangles(_cube(corner_indices=[7], corner_sharpness=[10.0]), "catmullClark", 3)
    assert np.linalg.norm(result["positions"].reshape(-1, 3) - [1, 1, 1], axis=-1).min() < 1e-12


def test_face_varying_uvs_are_refined_linearly_and_face_ids_kept():
    uvs = np.array([[0, 0], [1, 0], [1, 1], [0, 1]] * 6, np.float64)
    result = refined_triangles(_cube(uvs=uvs), "catmullClark", 2)
    assert result["uvs"].min() == 0 and result["uvs"].max() == 1
    np.testing.assert_array_equal(np.bincount(result["face_ids"]), np.full(6, 2 * 16))
    # The quarter-face of corner 0 of face 0 covers uv [0, 1/2]^2.
    assert set(np.round(result["uvs"][:8].reshape(-1, 2), 6).ravel()) <= {0.0, 0.25, 0.5}


def test_invalid_arguments():
    with pytest.raises(ValueError, match="at least one level"):
        refined_triangles(_cube(), "catmullClark", 0)
    with pytest.raises(ValueError, match="triangle mesh"):
        refined_triangles(_cube(), "loop", 1)


# ---------------------------------------------------------------------------------------------
# Level choice (dicing)


def _camera(position, width=160, height=120, near=0.01) -> Camera:
    world_from_camera = np.eye(4)
    world_from_camera[:3, 3] = position  # looking down -Z
    return Camera(
        path="/Cam",
        world_from_camera=world_from_camera,
        focal_length=50.0,
        horizontal_aperture=36.0,
        vertical_aperture=27.0,
        horizontal_aperture_offset=0.0,
        vertical_aperture_offset=0.0,
        clipping_range=(near, 1000.0),
        width=width,
        height=height,
    )


def test_projected_length_bound_and_levels():
    """One unit edge facing a camera 10 units away (its nearest point possibly 9.5 away):
    f (1 + tan^2 corner) / 9.5 pixels."""
    views = dicing.views_from_cameras({"/Cam": _camera([0, 0, 10])})
    focal = 50 / 36 * 160 * (1 + (18**2 + 13.5**2) / 50**2)
    length = dicing.max_projected_length(np.array([[-0.5, 0, 0]]), np.array([[0.5, 0, 0]]), np.eye(4)[None], views)
    assert length == pytest.approx(focal / 9.5)
    assert dicing.level_for_pixels(0.9) == 0
    assert dicing.level_for_pixels(2.0) == 1
    assert dicing.level_for_pixels(2.01) == 2
    assert dicing.level_for_pixels(1e30) == dicing.MAX_LEVEL


def test_projected_lengths_per_placement_match_one_at_a_time():
    """Many instances evaluated in chunks: each placement's longest edge is the one it has alone."""
    rng = np.random.default_rng(4)
    placements = np.tile(np.eye(4), (300, 1, 1))
    placements[:, :3, 3] = rng.uniform(-20, 20, (300, 3))
    placements[:, :3, :3] *= rng.uniform(0.5, 2.0, (300, 1, 1))
    views = dicing.views_from_cameras({"/A": _camera([0, 0, 30]), "/B": _camera([5, 1, -25])})
    edges = _cube_edges()
    starts, ends = CUBE_POINTS[edges[:, 0]], CUBE_POINTS[edges[:, 1]]
    one_at_a_time = [dicing.max_projected_length(starts, ends, placements[i : i + 1], views) for i in range(300)]
    np.testing.assert_allclose(dicing.projected_lengths(starts, ends, placements, views), one_at_a_time)
    assert dicing.max_projected_length(starts, ends, placements, views) == pytest.approx(max(one_at_a_time))


def test_placements_outside_every_frustum_set_no_rate():
    """A cube in front of the camera, one behind it, one beside the frustum and one straddling its
    edge: only the ones reaching into the frustum have a projected length (what no camera sees
    takes the coarsest level)."""
    views = dicing.views_from_cameras({"/Cam": _camera([0, 0, 10])})  # looking down -Z
    half_width = 10 * 18 / 50  # tan(half angle) x distance at z = 0
    placements = np.tile(np.eye(4), (4, 1, 1))
    placements[:, :3, 3] = [[0, 0, 0], [0, 0, 20], [half_width + 3, 0, 0], [half_width + 0.5, 0, 0]]
    edges = _cube_edges()
    lengths = dicing.projected_lengths(CUBE_POINTS[edges[:, 0]], CUBE_POINTS[edges[:, 1]], placements, views)
    assert lengths[0] > 1 and lengths[3] > 1
    assert lengths[1] == 0 and lengths[2] == 0


def test_each_instance_is_refined_for_its_own_size_on_screen():
    """Two PointInstancer instances of one subdivision cube, one by the camera and one far away:
    the near one is refined as the cube alone at its place is, the far one less (before, every
    instance took the nearest one's level and a shot of a thousand teapots ran out of memory)."""
    stage, _ = cube_cage_stage(camera_distance=3.0)
    instancer = UsdGeom.PointInstancer.Define(stage, "/Many")
    stage.DefinePrim("/Many/Prototypes", "Scope")
    prototype = stage.DefinePrim("/Many/Prototypes/Cube")
    prototype.GetReferences().AddInternalReference("/Cube")
    UsdGeom.Imageable(prototype).CreateVisibilityAttr(UsdGeom.Tokens.inherited)
    instancer.CreatePrototypesRel().SetTargets([prototype.GetPath()])
    instancer.CreatePositionsAttr([(0, 0, 0), (0, 0, -60)])
    instancer.CreateProtoIndicesAttr([0, 0])
    UsdGeom.Imageable(stage.GetPrimAtPath("/Cube")).MakeInvisible()
    geometry, warnings, _ = _read(stage)
    assert not warnings
    counts = np.bincount(geometry.object_ids)
    assert counts[1] < counts[0] / 4  # at least a level coarser

    near, _ = cube_cage_stage(camera_distance=3.0)
    alone, _, _ = _read(near)
    np.testing.assert_array_equal(geometry.positions[geometry.object_ids == 0], alone.positions)
    np.testing.assert_array_equal(geometry.normals[geometry.object_ids == 0], alone.normals)


def test_many_instances_are_placed_in_chunks_identically(monkeypatch):
    """Placing instances a few at a time (bounded temporaries) gives the same soup as all at once."""
    stage, _ = cube_cage_stage(camera_distance=3.0)
    instancer = UsdGeom.PointInstancer.Define(stage, "/Many")
    instancer.CreatePrototypesRel().SetTargets(["/Cube"])
    instancer.CreatePositionsAttr([(x, 0, -4.0) for x in range(-3, 4)])
    instancer.CreateOrientationsAttr([Gf.Quath(1, 0, 0, 0)] * 6 + [Gf.Quath(0, 0, 1, 0)])
    instancer.CreateScalesAttr([(1, 1, 1)] * 6 + [(-1, 1, 1)])  # one mirrored instance
    instancer.CreateProtoIndicesAttr([0] * 7)
    whole, _, _ = _read(stage)
    monkeypatch.setattr(geometry_module, "_PLACE_TRIANGLES", 1)
    chunked, _, _ = _read(stage)
    for name in ("positions", "normals", "uvs", "material_ids", "object_ids"):
        np.testing.assert_array_equal(getattr(chunked, name), getattr(whole, name))


# ---------------------------------------------------------------------------------------------
# USD stages


def _read(stage, width=160, height=120):
    scene = read_scene(stage, "test", width=width, height=height)
    return scene.geometry, scene.warnings, scene.cameras["/Cam"]


@pytest.mark.parametrize("left_handed", [False, True])
def test_usd_subdivision_mesh_is_refined_outward(left_handed):
    geometry, warnings, _ = _read(cube_cage_stage(left_handed=left_handed)[0])
    assert not warnings
    p = geometry.positions.astype(np.float64)
    assert len(p) > 6 * 2 * 16
    radius = np.linalg.norm(p.reshape(-1, 3), axis=-1)
    assert radius.min() >= 68 / 81 - 1e-6 and radius.max() <= np.sqrt(3) / 2 + 1e-6
    centre = p.mean(axis=1)
    assert np.all(np.sum(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]) * centre, axis=-1) > 0)
    assert np.all(np.sum(geometry.normals * p, axis=-1) > 0)


def test_usd_polygonal_and_bilinear_meshes_are_the_cage():
    for scheme in ("none", "bilinear"):
        geometry, _, _ = _read(cube_cage_stage(scheme=scheme)[0])
        assert geometry.num_triangles == 12


def test_usd_creases_and_corners_are_read():
    stage, mesh = cube_cage_stage()
    edges = _cube_edges()
    mesh.CreateCreaseIndicesAttr(edges.ravel().tolist())
    mesh.CreateCreaseLengthsAttr([2] * 12)
    mesh.CreateCreaseSharpnessesAttr([10.0] * 12)
    geometry, warnings, _ = _read(stage)
    assert not warnings
    np.testing.assert_allclose(np.abs(geometry.positions).max(axis=-1), 1.0, atol=1e-6)

    # One chain round the top face, its sharpness given per crease and per edge: the same
    # surface as the four edges given to the refinement directly.
    loop = [[4, 6], [6, 7], [7, 5], [5, 4]]
    for sharpnesses in ([10.0], [10.0] * 4):
        stage, mesh = cube_cage_stage()
        mesh.CreateCreaseIndicesAttr([4, 6, 7, 5, 4])
        mesh.CreateCreaseLengthsAttr([5])
        mesh.CreateCreaseSharpnessesAttr(sharpnesses)
        geometry, warnings, _ = _read(stage)
        assert not warnings
        level = round(np.log(geometry.num_triangles / 12) / np.log(4))
        expected = refined_triangles(_cube(crease_edges=loop, crease_sharpness=np.full(4, 10.0)), "catmullClark", level)
        np.testing.assert_allclose(geometry.positions, expected["positions"], atol=1e-6)

    stage, mesh = cube_cage_stage()
    mesh.CreateCornerIndicesAttr([7])
    mesh.CreateCornerSharpnessesAttr([10.0])
    geometry, _, _ = _read(stage)
    assert np.linalg.norm(geometry.positions.reshape(-1, 3) - [1, 1, 1], axis=-1).min() < 1e-6

    stage, mesh = cube_cage_stage()
    mesh.CreateCreaseIndicesAttr([0, 1, 3])
    mesh.CreateCreaseLengthsAttr([2])
    mesh.CreateCreaseSharpnessesAttr([1.0])
    _, warnings, _ = _read(stage)
    assert any("creases ignored" in w for w in warnings)


def test_planar_cage_stops_at_level_one():
    """A flat quad with the default (catmullClark) scheme: the limit is the quad, refined once."""
    stage, _ = cube_cage_stage()
    flat = UsdGeom.Mesh.Define(stage, "/Flat")
    flat.CreatePointsAttr([(-1, -1, -2), (1, -1, -2), (1, 1, -2), (-1, 1, -2)])
    flat.CreateFaceVertexCountsAttr([4])
    flat.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    stage.RemovePrim("/Cube")
    geometry, _, _ = _read(stage)
    assert geometry.num_triangles == 8
    np.testing.assert_allclose(geometry.positions[..., 2], -2.0)


def test_triangle_budget_is_bounded_with_a_warning(monkeypatch):
    monkeypatch.setattr(dicing, "TRIANGLE_BUDGET", 200)
    geometry, warnings, _ = _read(cube_cage_stage(camera_distance=3.0)[0])
    assert geometry.num_triangles == triangle_count(np.full(6, 4), "catmullClark", 2) == 192
    assert len(warnings) == 1 and "over the budget of 200 per mesh; refined to level 2" in warnings[0]


def test_no_camera_uses_the_fallback_level():
    stage, _ = cube_cage_stage()
    stage.RemovePrim("/Cam")
    warnings: list[str] = []
    geometry, _ = read_geometry(stage, DEFAULT, MaterialLibrary(stage, warnings), warnings)
    assert geometry.num_triangles == triangle_count(np.full(6, 4), "catmullClark", dicing.FALLBACK_LEVEL)


def test_sphere_silhouette_within_half_a_pixel_of_the_limit():
    """A sphere from a cube cage seen by the bake camera: the outline of the refined triangles is
    within half a pixel of the limit surface's (the limit approximated two levels finer, with
    its vertices on the limit surface; the shape is convex, so outlines are convex hulls)."""
    stage, _ = cube_cage_stage(camera_distance=3.0)
    geometry, _, camera = _read(stage, 160, 120)
    level = round(np.log(geometry.num_triangles / 12) / np.log(4))
    assert level >= 3
    reference = refined_triangles(_cube(), "catmullClark", level + 2)["positions"]
    assert silhouette_error(camera, geometry.positions, reference) < 0.5


@pytest.mark.parametrize(
    "points, indices, message",
    [
        (
            [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (np.nan, 0, 0)],
            [0, 1, 2, 3, 0, 1, 4],
            "non-finite points cannot be subdivided",
        ),
        ([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)], [0, 1, 2, 3, 0, 0, 1], "repeated vertex cannot be subdivided"),
    ],
)
def test_degenerate_cages_render_as_the_cage(points, indices, message):
    """A NaN point would spread over the refined surface and a repeated vertex makes a zero-length
    edge: such meshes render as their cage (its bad triangle dropped), with a warning."""
    stage, _ = cube_cage_stage()
    stage.RemovePrim("/Cube")
    mesh = UsdGeom.Mesh.Define(stage, "/Bad")
    mesh.CreatePointsAttr(points)
    mesh.CreateFaceVertexCountsAttr([4, 3])
    mesh.CreateFaceVertexIndicesAttr(indices)
    geometry, warnings, _ = _read(stage)
    assert geometry.num_triangles == 2
    assert any(message in w for w in warnings) and any("dropped 1 degenerate" in w for w in warnings)


@pytest.mark.parametrize("focal_length", [0.0, -1.0, float("nan")])
def test_a_camera_with_no_focal_length_sets_no_dicing_rate(focal_length):
    # Found by the stage fuzzer: focalLength 0 divided by zero here and ended the bake in a traceback.
    broken = dataclasses.replace(_camera([0, 0, 10]), focal_length=focal_length)
    assert dicing.views_from_cameras({"/Broken": broken}) == []
    assert len(dicing.views_from_cameras({"/Broken": broken, "/Fine": _camera([0, 0, 10])})) == 1
