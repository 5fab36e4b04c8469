"""The USD walker's geometry: triangulation, orientation, primvars, transforms, instancing,
implicit gprims, materials per face, and what is dropped. Values are hand-computed."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, Vt

from pipeline.scene.geometry import read_geometry
from pipeline.scene.materials import MaterialLibrary
from pipeline.scene.tessellate import NUM_SEGMENTS

DEFAULT = Usd.TimeCode.Default()
UNIT_SQUARE = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)]


def _read(stage: Usd.Stage):
    """(geometry, objects, materials, warnings) of an in-memory stage."""
    warnings: list[str] = []
    library = MaterialLibrary(stage, warnings)
    geometry, objects = read_geometry(stage, DEFAULT, library, warnings)
    return geometry, objects, library.materials, warnings


def _mesh(stage: Usd.Stage, path: str, points, counts, indices) -> UsdGeom.Mesh:
    """A polygonal mesh (subdivisionScheme 'none': subdivision surfaces are refined, see
    tests/test_subdivision.py)."""
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(points)
    mesh.CreateFaceVertexCountsAttr(counts)
    mesh.CreateFaceVertexIndicesAttr(indices)
    mesh.CreateSubdivisionSchemeAttr("none")
    return mesh


def _quad(stage: Usd.Stage, path: str = "/Quad") -> UsdGeom.Mesh:
    """Unit square in z = 0, counter-clockwise seen from +Z."""
    return _mesh(stage, path, UNIT_SQUARE, [4], [0, 1, 2, 3])


def _geometric_normals(geometry) -> np.ndarray:
    p = geometry.positions.astype(np.float64)
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return cross / np.linalg.norm(cross, axis=-1, keepdims=True)


def _areas(geometry) -> np.ndarray:
    p = geometry.positions.astype(np.float64)
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=-1)


# ---------------------------------------------------------------------------------------------
# Topology and orientation


def test_fan_triangulation_of_quads_pentagons_and_short_faces():
    stage = Usd.Stage.CreateInMemory()
    pentagon = [(np.cos(a), np.sin(a), 0.0) for a in np.linspace(0, 2 * np.pi, 6)[:5]]
    # A quad, a pentagon and a 2-vertex face (no triangle).
    points = UNIT_SQUARE + pentagon
    _mesh(stage, "/M", points, [4, 5, 2], [0, 1, 2, 3, 4, 5, 6, 7, 8, 4, 5])
    geometry, _, _, _ = _read(stage)
    assert geometry.num_triangles == 2 + 3
    corners = np.asarray(points, np.float32)
    expected = corners[[[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7], [4, 7, 8]]]
    np.testing.assert_allclose(geometry.positions, expected, atol=1e-6)
    assert np.isclose(_areas(geometry)[:2].sum(), 1.0)
    assert np.isclose(_areas(geometry)[2:].sum(), 2.5 * np.sin(2 * np.pi / 5))  # regular pentagon


def test_hole_indices_are_rendered_with_a_warning():
    stage = Usd.Stage.CreateInMemory()
    mesh = _mesh(stage, "/M", UNIT_SQUARE + [(2, 0, 0), (2, 1, 0)], [4, 4], [0, 1, 2, 3, 1, 4, 5, 2])
    mesh.CreateHoleIndicesAttr([1])
    geometry, _, _, warnings = _read(stage)
    assert geometry.num_triangles == 4
    assert any("holeIndices" in w and "/M" in w for w in warnings)


@pytest.mark.parametrize("orientation, expected_z", [("rightHanded", 1.0), ("leftHanded", -1.0)])
def test_left_handed_meshes_face_the_other_way(orientation, expected_z):
    stage = Usd.Stage.CreateInMemory()
    _quad(stage).CreateOrientationAttr(orientation)
    geometry, _, _, _ = _read(stage)
    np.testing.assert_allclose(_geometric_normals(geometry), [[0, 0, expected_z]] * 2, atol=1e-6)
    np.testing.assert_allclose(geometry.normals.reshape(-1, 3), [[0, 0, expected_z]] * 6, atol=1e-6)


def test_smooth_normals_unless_subdivision_scheme_is_none():
    """A 'bilinear' cage keeps smooth normals (Catmull-Clark and Loop are refined instead)."""
    stage = Usd.Stage.CreateInMemory()
    cube_points = [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    # Six outward quads of the cube [-1, 1]^3 (point index = 4x + 2y + z over {0, 1}).
    faces = [0, 1, 3, 2, 4, 6, 7, 5, 0, 4, 5, 1, 2, 3, 7, 6, 0, 2, 6, 4, 1, 5, 7, 3]
    _mesh(stage, "/Smooth", cube_points, [4] * 6, faces).CreateSubdivisionSchemeAttr("bilinear")
    _mesh(stage, "/Flat", cube_points, [4] * 6, faces)
    geometry, _, _, _ = _read(stage)
    positions, normals = geometry.positions, geometry.normals
    first = geometry.object_ids == 0
    # Smooth: three equal faces meet at each corner -> normal = corner / sqrt(3).
    np.testing.assert_allclose(normals[first], positions[first] / np.sqrt(3), atol=1e-6)
    # Flat: every corner carries its face's normal, which is the geometric one, outward.
    flat_normals = normals[~first]
    np.testing.assert_allclose(flat_normals, np.repeat(_geometric_normals(geometry)[~first, None], 3, 1), atol=1e-6)
    assert (np.einsum("tci,tci->tc", flat_normals, positions[~first]) > 0).all()


# ---------------------------------------------------------------------------------------------
# Primvars


def _set_st(mesh: UsdGeom.Mesh, values, interpolation: str, indices=None) -> None:
    primvar = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, interpolation)
    primvar.Set(values)
    if indices is not None:
        primvar.SetIndices(Vt.IntArray(indices))


def _two_quads(stage: Usd.Stage) -> UsdGeom.Mesh:
    """Two unit quads side by side: points 0-5, faces (0,1,4,3) and (1,2,5,4)."""
    points = [(0, 0, 0), (1, 0, 0), (2, 0, 0), (0, 1, 0), (1, 1, 0), (2, 1, 0)]
    return _mesh(stage, "/M", points, [4, 4], [0, 1, 4, 3, 1, 2, 5, 4])


# Triangle corners of _two_quads: fan (0,1,2),(0,2,3) of face corners 0-3, then 4-7.
_CORNERS = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
_POINT_OF_CORNER = np.array([0, 1, 4, 3, 1, 2, 5, 4])
_FACE_OF_TRIANGLE = np.array([0, 0, 1, 1])


@pytest.mark.parametrize("interpolation", ["constant", "uniform", "vertex", "varying", "faceVarying"])
def test_st_primvar_each_interpolation(interpolation):
    stage = Usd.Stage.CreateInMemory()
    mesh = _two_quads(stage)
    size = {"constant": 1, "uniform": 2, "vertex": 6, "varying": 6, "faceVarying": 8}[interpolation]
    values = np.stack((np.arange(size), 10.0 + np.arange(size)), -1).astype(np.float32)
    _set_st(mesh, Vt.Vec2fArray.FromNumpy(values), interpolation)
    geometry, _, _, _ = _read(stage)
    lookup = {
        "constant": np.zeros_like(_CORNERS),
        "uniform": np.repeat(_FACE_OF_TRIANGLE[:, None], 3, 1),
        "vertex": _POINT_OF_CORNER[_CORNERS],
        "varying": _POINT_OF_CORNER[_CORNERS],
        "faceVarying": _CORNERS,
    }[interpolation]
    np.testing.assert_array_equal(geometry.uvs, values[lookup])


def test_indexed_face_varying_st():
    stage = Usd.Stage.CreateInMemory()
    mesh = _two_quads(stage)
    values = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    indices = [0, 1, 2, 3, 3, 2, 1, 0]
    _set_st(mesh, Vt.Vec2fArray.FromNumpy(values), "faceVarying", indices)
    geometry, _, _, _ = _read(stage)
    np.testing.assert_array_equal(geometry.uvs, values[np.asarray(indices)[_CORNERS]])


def test_short_primvar_is_ignored_with_a_warning():
    stage = Usd.Stage.CreateInMemory()
    _set_st(_two_quads(stage), Vt.Vec2fArray([(0.5, 0.5)] * 3), "vertex")
    geometry, _, _, warnings = _read(stage)
    assert np.all(geometry.uvs == 0)
    assert any("st" in w and "vertex" in w for w in warnings)


def test_primvars_normals_win_over_the_normals_attribute():
    stage = Usd.Stage.CreateInMemory()
    mesh = _quad(stage)
    mesh.CreateNormalsAttr([(1, 0, 0)] * 4)
    mesh.SetNormalsInterpolation("vertex")
    tilted = np.array([0.0, 0.6, 0.8], np.float32)
    UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("normals", Sdf.ValueTypeNames.Normal3fArray, "uniform").Set(
        [Gf.Vec3f(0.0, 0.6, 0.8)]
    )
    geometry, _, _, _ = _read(stage)
    np.testing.assert_allclose(geometry.normals.reshape(-1, 3), [tilted] * 6, atol=1e-6)


def test_normals_attribute_with_its_interpolation():
    stage = Usd.Stage.CreateInMemory()
    mesh = _quad(stage)
    normals = np.array([[0, 0, 1], [0, 0.6, 0.8], [0.6, 0, 0.8], [0, -0.6, 0.8]], np.float32)
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(normals))
    mesh.SetNormalsInterpolation("vertex")
    geometry, _, _, _ = _read(stage)
    np.testing.assert_allclose(geometry.normals, normals[[[0, 1, 2], [0, 2, 3]]], atol=1e-6)


# ---------------------------------------------------------------------------------------------
# Transforms


def test_nested_transforms_translate_rotate_scale():
    stage = Usd.Stage.CreateInMemory()
    parent = UsdGeom.Xform.Define(stage, "/P")
    parent.AddTranslateOp().Set((10, 0, 0))
    child = UsdGeom.Xform.Define(stage, "/P/C")
    child.AddRotateZOp().Set(90.0)
    child.AddScaleOp().Set((2, 3, 1))
    _quad(stage, "/P/C/Quad")
    geometry, _, _, _ = _read(stage)
    # p -> (10, 0, 0) + Rz(90) (2x, 3y, z) = (10 - 3y, 2x, z)
    square = np.asarray(UNIT_SQUARE, np.float64)
    world = np.stack((10 - 3 * square[:, 1], 2 * square[:, 0], square[:, 2]), -1)
    np.testing.assert_allclose(geometry.positions, world[[[0, 1, 2], [0, 2, 3]]], atol=1e-5)


def test_non_uniform_scale_transforms_normals_by_the_inverse_transpose():
    stage = Usd.Stage.CreateInMemory()
    # The plane x + z = 1 (normal (1, 0, 1)/sqrt2), counter-clockwise seen from its normal side.
    mesh = _mesh(stage, "/M", [(1, 0, 0), (0, 1, 1), (0, 0, 1)], [3], [0, 1, 2])
    mesh.CreateSubdivisionSchemeAttr("none")
    mesh.AddScaleOp().Set((2, 1, 1))
    geometry, _, _, _ = _read(stage)
    # Scaled plane x/2 + z = 1 has normal (1/2, 0, 1) normalised.
    expected = np.array([0.5, 0.0, 1.0]) / np.linalg.norm([0.5, 0.0, 1.0])
    np.testing.assert_allclose(geometry.normals.reshape(-1, 3), [expected] * 3, atol=1e-6)
    np.testing.assert_allclose(_geometric_normals(geometry)[0], expected, atol=1e-6)


def test_negative_scale_rewinds_so_geometric_and_shading_normals_agree():
    stage = Usd.Stage.CreateInMemory()
    mesh = _quad(stage)
    mesh.CreateNormalsAttr([(0, 0, 1)] * 4)
    mesh.SetNormalsInterpolation("vertex")
    mesh.AddScaleOp().Set((1, 1, -1))  # mirror in z: the front now faces -Z
    geometry, _, _, _ = _read(stage)
    np.testing.assert_allclose(_geometric_normals(geometry), [[0, 0, -1]] * 2, atol=1e-6)
    np.testing.assert_allclose(geometry.normals.reshape(-1, 3), [[0, 0, -1]] * 6, atol=1e-6)
    # Same corner set as the unmirrored quad (mirroring z = 0 changes no position).
    assert sorted(map(tuple, geometry.positions.reshape(-1, 3).tolist())) == sorted(
        map(tuple, np.asarray(UNIT_SQUARE, np.float32)[[0, 2, 1, 0, 3, 2]].tolist())
    )


# ---------------------------------------------------------------------------------------------
# Instancing


def test_instanceable_references_expand_to_world_placed_copies():
    stage = Usd.Stage.CreateInMemory()
    asset = UsdGeom.Xform.Define(stage, "/Asset")
    _quad(stage, "/Asset/Quad")
    asset.GetPrim().SetSpecifier(Sdf.SpecifierClass)
    offsets = [(0, 0, 0), (5, 0, 0), (0, 7, 0)]
    for i, offset in enumerate(offsets):
        instance = UsdGeom.Xform.Define(stage, f"/Instance{i}")
        instance.GetPrim().GetReferences().AddInternalReference("/Asset")
        instance.GetPrim().SetInstanceable(True)
        instance.AddTranslateOp().Set(offset)
    geometry, objects, _, _ = _read(stage)
    assert geometry.num_triangles == 2 * len(offsets)
    assert [o.path for o in objects] == [f"/Instance{i}/Quad" for i in range(3)]
    for i, offset in enumerate(offsets):
        corners = geometry.positions[geometry.object_ids == i].reshape(-1, 3)
        np.testing.assert_allclose(corners.min(0), offset, atol=1e-6)
        np.testing.assert_allclose(corners.max(0), np.add(offset, (1, 1, 0)), atol=1e-6)


def test_point_instancer_places_each_prototype_per_instance():
    stage = Usd.Stage.CreateInMemory()
    instancer = UsdGeom.PointInstancer.Define(stage, "/World/PI")
    instancer.AddTranslateOp().Set((0, 0, 100))
    prototypes = UsdGeom.Scope.Define(stage, "/World/PI/Prototypes")
    prototypes.MakeInvisible()  # a common way to hide prototypes; instances must still render
    quad = _quad(stage, "/World/PI/Prototypes/Quad")
    quad.AddTranslateOp().Set((0, 0, 1))  # the prototype root's own transform applies once
    UsdGeom.Cube.Define(stage, "/World/PI/Prototypes/Cube").CreateSizeAttr(0.5)
    instancer.CreatePrototypesRel().SetTargets([quad.GetPath(), Sdf.Path("/World/PI/Prototypes/Cube")])
    instancer.CreateProtoIndicesAttr([0, 1, 0, 0])
    instancer.CreatePositionsAttr([(1, 0, 0), (2, 0, 0), (3, 0, 0), (4, 0, 0)])
    instancer.DeactivateId(2)
    geometry, objects, _, _ = _read(stage)
    assert geometry.num_triangles == 2 * 2 + 12
    assert [o.path for o in objects] == [
        "/World/PI[0]/World/PI/Prototypes/Quad",
        "/World/PI[3]/World/PI/Prototypes/Quad",
        "/World/PI[1]/World/PI/Prototypes/Cube",
    ]
    for object_id, x, z in [(0, 1, 101), (1, 4, 101), (2, 2, 100)]:
        corners = geometry.positions[geometry.object_ids == object_id].reshape(-1, 3)
        centre = (corners.min(0) + corners.max(0)) / 2
        expected_centre = (x + 0.5, 0.5, z) if object_id < 2 else (x, 0, z)
        np.testing.assert_allclose(centre, expected_centre, atol=1e-5)


# ---------------------------------------------------------------------------------------------
# Implicit gprims


def _define(stage, type_name, **attributes):
    prim = stage.DefinePrim("/G", type_name)
    for name, value in attributes.items():
        prim.GetAttribute(name).Set(value)
    return prim


_IMPLICIT_CASES = [
    # type, attributes, analytic area, spine axis (None: no axis) and half-extent along it
    ("Sphere", {"radius": 2.0}, 4 * np.pi * 4, None),
    ("Cube", {"size": 3.0}, 6 * 9, None),
    ("Cylinder", {"radius": 1.0, "height": 3.0, "axis": "X"}, 2 * np.pi * 3 + 2 * np.pi, ("X", 1.5)),
    ("Cone", {"radius": 1.0, "height": 2.0, "axis": "Y"}, np.pi * np.sqrt(5) + np.pi, ("Y", 1.0)),
    ("Capsule", {"radius": 0.5, "height": 1.0, "axis": "Z"}, np.pi + np.pi, ("Z", 1.0)),
    (
        "Cylinder_1",
        {"radiusBottom": 1.0, "radiusTop": 0.5, "height": 2.0, "axis": "Z"},
        np.pi * 1.5 * np.sqrt(4.25) + np.pi * 1.25,
        ("Z", 1.0),
    ),
    ("Plane", {"width": 2.0, "length": 3.0, "axis": "Y"}, 6.0, None),
]


@pytest.mark.parametrize("type_name, attributes, area, spine", _IMPLICIT_CASES, ids=[c[0] for c in _IMPLICIT_CASES])
def test_implicit_gprims_area_normals_and_axis(type_name, attributes, area, spine):
    stage = Usd.Stage.CreateInMemory()
    _define(stage, type_name, **attributes)
    geometry, objects, _, _ = _read(stage)
    # Polygonal approximation of a round surface is slightly smaller: error ~ (2 pi / N)^2 / 6.
    assert _areas(geometry).sum() == pytest.approx(area, rel=2 * (2 * np.pi / NUM_SEGMENTS) ** 2)
    assert _areas(geometry).sum() <= area * (1 + 1e-6)
    np.testing.assert_allclose(np.linalg.norm(geometry.normals, axis=-1), 1.0, atol=1e-5)
    centroid = geometry.positions.mean(axis=1)
    if type_name == "Plane":
        np.testing.assert_allclose(geometry.normals.reshape(-1, 3), [[0, 1, 0]] * 6, atol=1e-6)
        np.testing.assert_allclose(np.ptp(geometry.positions.reshape(-1, 3), 0), [2, 0, 3], atol=1e-6)
        assert objects[0].double_sided  # Plane's fallback doubleSided is true
    else:
        # Outward: shading and geometric normals point away from the centre.
        assert (np.einsum("tci,tci->tc", geometry.normals, geometry.positions) > -1e-6).all()
        assert (np.einsum("ti,ti->t", _geometric_normals(geometry), centroid) > 0).all()
        assert not objects[0].double_sided
    if spine is not None:
        axis, half = spine
        extent = np.abs(geometry.positions.reshape(-1, 3)).max(0)
        assert extent["XYZ".index(axis)] == pytest.approx(half, rel=1e-6)


def test_sphere_normals_are_analytic():
    stage = Usd.Stage.CreateInMemory()
    _define(stage, "Sphere", radius=3.0)
    geometry, _, _, _ = _read(stage)
    np.testing.assert_allclose(geometry.normals, geometry.positions / 3.0, atol=1e-5)


# ---------------------------------------------------------------------------------------------
# Visibility, materials, dropped triangles


def test_invisible_and_guide_prims_are_skipped():
    stage = Usd.Stage.CreateInMemory()
    _quad(stage, "/Shown")
    UsdGeom.Xform.Define(stage, "/Hidden").MakeInvisible()
    _quad(stage, "/Hidden/Quad")
    _quad(stage, "/Guide").CreatePurposeAttr("guide")
    _quad(stage, "/Render").CreatePurposeAttr("render")
    _, objects, _, _ = _read(stage)
    assert [o.path for o in objects] == ["/Shown", "/Render"]


def _material(stage: Usd.Stage, path: str, color) -> UsdShade.Material:
    material = UsdShade.Material.Define(stage, path)
    shader = UsdShade.Shader.Define(stage, f"{path}/Surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(color)
    material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    return material


def test_materials_per_face_from_geom_subsets():
    stage = Usd.Stage.CreateInMemory()
    mesh = _two_quads(stage)
    red = _material(stage, "/Looks/Red", (1, 0, 0))
    blue = _material(stage, "/Looks/Blue", (0, 0, 1))
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(red)
    subset = UsdShade.MaterialBindingAPI(mesh.GetPrim()).CreateMaterialBindSubset("right", Vt.IntArray([1]))
    UsdShade.MaterialBindingAPI.Apply(subset.GetPrim()).Bind(blue)
    geometry, _, materials, _ = _read(stage)
    assert [materials[i].path for i in geometry.material_ids] == ["/Looks/Red"] * 2 + ["/Looks/Blue"] * 2


def test_display_color_without_material():
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.Gprim(_quad(stage)).CreateDisplayColorAttr([(0.2, 0.4, 0.6)])
    geometry, _, materials, _ = _read(stage)
    np.testing.assert_allclose(materials[geometry.material_ids[0]].diffuse_color.value, [0.2, 0.4, 0.6])


def test_double_sided_reaches_the_scene_object():
    stage = Usd.Stage.CreateInMemory()
    _quad(stage, "/One")
    _quad(stage, "/Two").CreateDoubleSidedAttr(True)
    _, objects, _, _ = _read(stage)
    assert [(o.path, o.double_sided) for o in objects] == [("/One", False), ("/Two", True)]


def test_degenerate_and_nan_triangles_dropped_with_one_warning():
    stage = Usd.Stage.CreateInMemory()
    nan = float("nan")
    points = UNIT_SQUARE + [(2, 0, 0), (3, 0, 0), (4, 0, 0), (nan, 0, 0)]
    # 2 good triangles, a collinear one, a repeated-point one, and one with a NaN corner.
    _mesh(stage, "/Bad", points, [4, 3, 3, 3], [0, 1, 2, 3, 4, 5, 6, 4, 4, 5, 0, 1, 7])
    geometry, _, _, warnings = _read(stage)
    assert geometry.num_triangles == 2
    assert np.isfinite(geometry.normals).all()
    dropped = [w for w in warnings if "dropped" in w]
    assert len(dropped) == 1 and "/Bad" in dropped[0] and " 3 " in dropped[0]


def test_invalid_topology_is_skipped_with_a_warning():
    stage = Usd.Stage.CreateInMemory()
    _mesh(stage, "/Broken", UNIT_SQUARE, [4], [0, 1, 2, 9])
    _quad(stage, "/Fine")
    _geometry, objects, _, warnings = _read(stage)
    assert [o.path for o in objects] == ["/Fine"]
    assert any("/Broken" in w for w in warnings)


def test_nested_point_instancers_compose_their_transforms():
    stage = Usd.Stage.CreateInMemory()
    outer = UsdGeom.PointInstancer.Define(stage, "/Outer")
    inner = UsdGeom.PointInstancer.Define(stage, "/Outer/Protos/Inner")
    UsdGeom.Cube.Define(stage, "/Outer/Protos/Inner/Protos/Cube").CreateSizeAttr(0.1)
    inner.CreatePrototypesRel().SetTargets(["/Outer/Protos/Inner/Protos/Cube"])
    inner.CreateProtoIndicesAttr([0, 0])
    inner.CreatePositionsAttr([(0, 1, 0), (0, 2, 0)])
    outer.CreatePrototypesRel().SetTargets([inner.GetPath()])
    outer.CreateProtoIndicesAttr([0, 0])
    outer.CreatePositionsAttr([(10, 0, 0), (20, 0, 0)])
    outer.CreateScalesAttr([(1, 1, 1), (1, 3, 1)])
    geometry, objects, _, _ = _read(stage)
    assert len(objects) == 4 and geometry.num_triangles == 4 * 12
    centres = [geometry.positions[geometry.object_ids == i].reshape(-1, 3).mean(0) for i in range(4)]
    np.testing.assert_allclose(centres, [(10, 1, 0), (10, 2, 0), (20, 3, 0), (20, 6, 0)], atol=1e-5)
    assert objects[3].path == "/Outer[1]/Outer/Protos/Inner[1]/Outer/Protos/Inner/Protos/Cube"


def test_inconsistent_point_instancer_is_skipped_with_a_warning():
    stage = Usd.Stage.CreateInMemory()
    instancer = UsdGeom.PointInstancer.Define(stage, "/PI")
    UsdGeom.Cube.Define(stage, "/PI/Protos/Cube")
    instancer.CreatePrototypesRel().SetTargets(["/PI/Protos/Cube"])
    instancer.CreateProtoIndicesAttr([0, 5])  # index 5: no such prototype
    instancer.CreatePositionsAttr([(0, 0, 0), (1, 0, 0)])
    _quad(stage)
    _, objects, _, warnings = _read(stage)
    assert [o.path for o in objects] == ["/Quad"]
    assert any("/PI" in w and "skipped" in w for w in warnings)


def test_varying_display_color_is_averaged_with_one_warning_per_surface():
    stage = Usd.Stage.CreateInMemory()
    mesh = _two_quads(stage)
    primvar = UsdGeom.Gprim(mesh).CreateDisplayColorPrimvar("uniform")
    primvar.Set([(1, 0, 0), (0, 0, 1)])
    geometry, _, materials, warnings = _read(stage)
    np.testing.assert_allclose(materials[geometry.material_ids[0]].diffuse_color.value, [0.5, 0, 0.5])
    assert sum("displayColor averaged" in w for w in warnings) == 1
