"""The bundled scenes: written USD opens, validates, and carries the published / designed content."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest
from pxr import Sdf, Usd, UsdGeom, UsdLux, UsdRender, UsdShade, UsdValidation

from pipeline.cli import COMMANDS
from pipeline.commands import scenes as scenes_command
from pipeline.errors import RelightError
from pipeline.scene import load_scene
from pipeline.scenes import (
    LAYERED_SCENES,
    SCENES,
    cornell_box,
    dome,
    example_light_edits,
    glossy,
    layered_edit_layers,
    write_light_edits,
)
from pipeline.scenes import set as set_scene
from pipeline.scenes.authoring import aim_rotation_xyz, place
from pipeline.scenes.colorimetry import (
    CMF_XYZ,
    D65,
    WAVELENGTHS_NM,
    emission_to_linear_rec709,
    linear_rec709_from_xyz_matrix,
    reflectance_to_linear_rec709,
)
from pipeline.scenes.lights import NEW_LIGHT_PATH, new_sphere_layer
from pipeline.scenes.meshes import MeshData, box, newell_normals, revolve, torus, uv_sphere
from pipeline.scenes.textures import brick_height, normal_map_from_height
from relight_torch.lights.light import LightKind

EXPECTED = {
    # name: (metersPerUnit, resolution, {light type: count}, number of materials)
    "cornell_box": (0.001, (512, 512), {"RectLight": 1}, 3),
    "glossy": (0.01, (640, 480), {"SphereLight": 2}, 7),
    "dome": (0.01, (640, 480), {"DomeLight": 1}, 7),
    "set": (0.01, (640, 480), {"DistantLight": 1, "RectLight": 1, "SphereLight": 2, "DiskLight": 1}, 5),
    "leaves": (0.01, (640, 480), {"SphereLight": 1, "DistantLight": 1}, 3),
}


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> dict[str, Path]:
    """Every bundled scene written once into one directory: name -> layer path."""
    directory = tmp_path_factory.mktemp("bundled")
    return {name: scene.write(directory) for name, scene in SCENES.items()}


@pytest.fixture(scope="module")
def stages(written) -> dict[str, Usd.Stage]:
    return {name: Usd.Stage.Open(str(path)) for name, path in written.items()}


def _validation_issues(stage: Usd.Stage) -> list[tuple[str, str]]:
    """(type, 'validator: message') for every issue all UsdValidation validators report."""
    registry = UsdValidation.ValidationRegistry()
    context = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators())
    return [
        (str(error.GetType()), f"{error.GetValidator().GetMetadata().name}: {error.GetMessage()}")
        for error in context.Validate(stage)
    ]


def _world_from_local(prim: Usd.Prim) -> np.ndarray:
    """(4, 4) column-vector world transform of a prim (Gf is row-vector: transpose)."""
    return np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default())).T


def _triangle_count(stage: Usd.Stage) -> int:
    """Triangles of every rendered mesh, instances (instanceable prims and PointInstancers) expanded."""

    def mesh_triangles(root: Usd.Prim, instance_proxies: bool) -> int:
        predicate = (
            Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate) if instance_proxies else Usd.PrimAllPrimsPredicate
        )
        total = 0
        iterator = iter(Usd.PrimRange(root, predicate))
        for prim in iterator:
            if prim.IsA(UsdGeom.PointInstancer):
                instancer = UsdGeom.PointInstancer(prim)
                counts = np.bincount(np.asarray(instancer.GetProtoIndicesAttr().Get()))
                targets = instancer.GetPrototypesRel().GetTargets()
                total += sum(
                    int(n) * mesh_triangles(stage.GetPrimAtPath(t), False) for n, t in zip(counts, targets, strict=True)
                )
                iterator.PruneChildren()
            elif prim.IsA(UsdGeom.Mesh):
                total += int(np.sum(np.asarray(UsdGeom.Mesh(prim).GetFaceVertexCountsAttr().Get()) - 2))
        return total

    return mesh_triangles(stage.GetPseudoRoot(), True)


# ---------------------------------------------------------------------------------------- every scene


@pytest.mark.parametrize("name", sorted(SCENES))
def test_scene_writes_a_valid_stage(name, written, stages):
    meters_per_unit, resolution, _, _ = EXPECTED[name]
    stage = stages[name]
    assert written[name] == written[name].parent / f"{name}.usda"
    assert stage.GetDefaultPrim().GetPath() == Sdf.Path("/World")
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(meters_per_unit)
    settings = UsdRender.Settings(stage.GetPrimAtPath(stage.GetMetadata("renderSettingsPrimPath")))
    assert tuple(settings.GetResolutionAttr().Get()) == resolution
    assert settings.GetCameraRel().GetTargets() == [Sdf.Path(SCENES[name].camera)]
    assert stage.GetPrimAtPath(SCENES[name].camera).IsA(UsdGeom.Camera)
    assert not [p for p in written[name].parent.iterdir() if p.name.startswith(".")], "temp file left behind"


@pytest.mark.parametrize("name", sorted(SCENES))
def test_scene_is_clean_under_usd_validation(name, stages):
    # No errors and, so far, no warnings either: nothing to justify.
    assert _validation_issues(stages[name]) == []


def test_validation_reports_a_binding_without_the_api(written):
    # The validators are live: the Cornell box with MaterialBindingAPI stripped must fail.
    text = written["cornell_box"].read_text().replace('prepend apiSchemas = ["MaterialBindingAPI"]', "")
    layer = Sdf.Layer.CreateAnonymous(".usda")
    layer.ImportFromString(text)
    issues = _validation_issues(Usd.Stage.Open(layer))
    assert len(issues) == 7 and all("MaterialBindingAPI" in message for _, message in issues)


@pytest.mark.parametrize("name", sorted(SCENES))
def test_scene_has_the_expected_lights_camera_and_materials(name, stages):
    _, _, light_types, num_materials = EXPECTED[name]
    prims = list(stages[name].Traverse())
    found = {}
    for prim in prims:
        if prim.HasAPI(UsdLux.LightAPI):
            found[prim.GetTypeName()] = found.get(prim.GetTypeName(), 0) + 1
    assert found == light_types
    assert sum(prim.IsA(UsdGeom.Camera) for prim in prims) == 1
    assert sum(prim.IsA(UsdShade.Material) for prim in prims) == num_materials
    for prim in prims:  # every binding has its API; every material is UsdPreviewSurface
        if prim.HasRelationship("material:binding"):
            assert prim.HasAPI(UsdShade.MaterialBindingAPI), prim.GetPath()
        if prim.IsA(UsdShade.Material):
            assert UsdShade.Material(prim).ComputeSurfaceSource()[0].GetIdAttr().Get() == "UsdPreviewSurface"


@pytest.mark.parametrize("name", sorted(SCENES))
def test_writing_twice_gives_the_same_layer(name, written, tmp_path):
    assert SCENES[name].write(tmp_path).read_text() == written[name].read_text()


# ---------------------------------------------------------------------------------------- colorimetry


def test_perfect_reflector_is_white_and_matrix_matches_iec_61966():
    assert reflectance_to_linear_rec709(np.array([380.0, 780.0]), np.ones(2)) == pytest.approx(np.ones(3), abs=1e-9)
    iec = np.array([[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]])
    np.testing.assert_allclose(linear_rec709_from_xyz_matrix(), iec, atol=1.5e-3)


def test_equal_energy_emission_has_the_rgb_of_illuminant_e():
    # Illuminant E has XYZ = (1, 1, 1); through the IEC matrix that is (1.2048, 0.9484, 0.9087).
    rgb = emission_to_linear_rec709(np.array([380.0, 780.0]), np.ones(2))
    np.testing.assert_allclose(rgb, [1.2048, 0.9484, 0.9087], atol=3e-3)
    assert rgb @ [0.2126, 0.7152, 0.0722] == pytest.approx(1.0, abs=1e-3)


def test_cie_tables_match_mitsuba_copy():
    import mitsuba as mi  # here, not at the top: importing mitsuba takes a while

    previous = mi.variant()
    mi.set_variant("scalar_spectral")
    try:
        expected = np.array([list(mi.cie1931_xyz(float(w))) for w in WAVELENGTHS_NM])
    finally:
        if previous:  # leave other tests in this process the variant they chose
            mi.set_variant(previous)
    np.testing.assert_allclose(CMF_XYZ, expected, rtol=1e-5, atol=1e-9)
    assert CMF_XYZ[np.searchsorted(WAVELENGTHS_NM, 555.0)] == pytest.approx([0.51205, 1.0, 0.00575])
    assert D65[np.searchsorted(WAVELENGTHS_NM, 560.0)] == 100.0
    assert D65[np.searchsorted(WAVELENGTHS_NM, 460.0)] == pytest.approx(117.812)


# ---------------------------------------------------------------------------------------- Cornell box


def _diffuse_color(stage: Usd.Stage, prim_path: str) -> np.ndarray:
    material, _ = UsdShade.MaterialBindingAPI(stage.GetPrimAtPath(prim_path)).ComputeBoundMaterial()
    return np.array(material.ComputeSurfaceSource()[0].GetInput("diffuseColor").Get())


def test_cornell_wall_colours_have_the_published_hue_and_range(stages):
    stage = stages["cornell_box"]
    red = _diffuse_color(stage, "/World/Geometry/LeftWall")
    green = _diffuse_color(stage, "/World/Geometry/RightWall")
    white = _diffuse_color(stage, "/World/Geometry/Floor")
    assert red[0] > 5 * red[1] and red[0] > 5 * red[2]
    assert green[1] > 4 * green[0] and green[1] > 4 * green[2]
    assert np.ptp(white) < 0.01
    # Each dominant channel lies between the paint's lowest and highest measured reflectance.
    for rgb, channel, paint in ((red, 0, "red"), (green, 1, "green"), (white, slice(None), "white")):
        spectrum = cornell_box.REFLECTANCE[paint]
        assert np.all((min(spectrum) <= rgb[channel]) & (rgb[channel] <= max(spectrum)))
    # The values the module documents.
    np.testing.assert_allclose(red, [0.4932, 0.0489, 0.0512], atol=1e-3)
    np.testing.assert_allclose(green, [0.0686, 0.3986, 0.0865], atol=1e-3)
    np.testing.assert_allclose(white, [0.7385, 0.7363, 0.7390], atol=1e-3)


def _ndc_x(stage: Usd.Stage, camera_path: str, world_points: np.ndarray) -> np.ndarray:
    """Horizontal normalised image coordinate (-1 left .. 1 right) of world points."""
    camera = UsdGeom.Camera(stage.GetPrimAtPath(camera_path)).GetCamera(Usd.TimeCode.Default())
    camera_from_world = np.linalg.inv(np.array(camera.transform).T)
    p_camera = world_points @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]
    return (camera.focalLength / (0.5 * camera.horizontalAperture)) * p_camera[:, 0] / -p_camera[:, 2]


def _mesh_corners(stage: Usd.Stage, path: str) -> np.ndarray:
    """(F, 4, 3) quad corners of a mesh in world space, in authored winding."""
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath(path))
    points = np.asarray(mesh.GetPointsAttr().Get(), np.float64)
    assert set(mesh.GetFaceVertexCountsAttr().Get()) == {4}
    return points[np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 4)]


def test_cornell_camera_sees_red_wall_left_and_green_right(stages):
    stage = stages["cornell_box"]
    centroids = np.array(
        [
            _mesh_corners(stage, f"/World/Geometry/{name}").reshape(-1, 3).mean(axis=0)
            for name in ("LeftWall", "RightWall", "TallBlock", "ShortBlock")
        ]
    )
    x = _ndc_x(stage, cornell_box.CAMERA, centroids)
    assert x[0] < -0.6 and x[1] > 0.6  # red wall left, green wall right, as photographed
    assert x[2] < 0 < x[3]  # tall block on the left, short block on the right
    assert UsdGeom.Mesh(stage.GetPrimAtPath("/World/Geometry/Floor")).GetOrientationAttr().Get() == "rightHanded"


def test_cornell_faces_point_into_the_box_and_out_of_the_blocks(stages):
    stage = stages["cornell_box"]
    center = cornell_box.box_center()
    for name in ("Floor", "Ceiling", "BackWall", "RightWall", "LeftWall"):
        corners = _mesh_corners(stage, f"/World/Geometry/{name}")
        assert np.all(np.einsum("fi,fi->f", newell_normals(corners), center - corners.mean(axis=1)) > 0), name
    for name in ("ShortBlock", "TallBlock"):
        corners = _mesh_corners(stage, f"/World/Geometry/{name}")
        outward = corners.mean(axis=1) - corners.reshape(-1, 3).mean(axis=0)
        assert np.all(np.einsum("fi,fi->f", newell_normals(corners), outward) > 0), name
    floor = _mesh_corners(stage, "/World/Geometry/Floor")[0]
    assert {tuple(np.round(p, 3)) for p in floor} == {(552.8, 0, 0), (0, 0, 0), (0, 0, 559.2), (549.6, 0, 559.2)}


def test_cornell_light_fills_the_published_opening_facing_down(stages):
    prim = stages["cornell_box"].GetPrimAtPath(cornell_box.LIGHT)
    light = UsdLux.RectLight(prim)
    world_from_light = _world_from_local(prim)
    half_w, half_h = light.GetWidthAttr().Get() / 2, light.GetHeightAttr().Get() / 2
    corners_local = np.array(
        [[-half_w, -half_h, 0, 1], [half_w, -half_h, 0, 1], [half_w, half_h, 0, 1], [-half_w, half_h, 0, 1]]
    )
    corners = (corners_local @ world_from_light.T)[:, :3]
    np.testing.assert_allclose([corners[:, 0].min(), corners[:, 0].max()], [213.0, 343.0], atol=1e-4)
    np.testing.assert_allclose([corners[:, 2].min(), corners[:, 2].max()], [227.0, 332.0], atol=1e-4)
    assert np.all((corners[:, 1] < 548.8) & (corners[:, 1] > 547.0))  # just below the ceiling
    np.testing.assert_allclose(-world_from_light[:3, 2], [0.0, -1.0, 0.0], atol=1e-6)  # emits down
    color = np.array(light.GetColorAttr().Get())
    assert color @ [0.2126, 0.7152, 0.0722] == pytest.approx(1.0, abs=2e-3)
    assert color[0] > color[1] > color[2]  # tungsten: reddish


def test_cornell_camera_is_the_published_one(stages):
    prim = stages["cornell_box"].GetPrimAtPath(cornell_box.CAMERA)
    camera = UsdGeom.Camera(prim)
    world_from_camera = _world_from_local(prim)
    np.testing.assert_allclose(world_from_camera[:3, 3], [278.0, 273.0, -800.0])
    np.testing.assert_allclose(-world_from_camera[:3, 2], [0.0, 0.0, 1.0], atol=1e-6)  # looks along +z
    np.testing.assert_allclose(world_from_camera[:3, 1], [0.0, 1.0, 0.0], atol=1e-6)  # +y up
    # 35 mm lens, 25 mm film: tenths of a millimetre in a millimetre stage.
    assert camera.GetFocalLengthAttr().Get() == pytest.approx(350.0)
    assert camera.GetHorizontalApertureAttr().Get() == camera.GetVerticalApertureAttr().Get() == pytest.approx(250.0)


# ---------------------------------------------------------------------------------------- glossy


def test_glossy_materials_textures_and_primitives(written, stages):
    stage = stages["glossy"]
    layer_dir = written["glossy"].parent
    shaders = {
        prim.GetPath().pathString: UsdShade.Shader(prim) for prim in stage.Traverse() if prim.IsA(UsdShade.Shader)
    }
    normal_tex = shaders["/World/Materials/Bricks/normalTexture"]
    assert normal_tex.GetInput("sourceColorSpace").Get() == "raw"
    assert tuple(normal_tex.GetInput("scale").Get()) == (2, 2, 2, 1)
    assert tuple(normal_tex.GetInput("bias").Get()) == (-1, -1, -1, 0)
    assert shaders["/World/Materials/Bricks/diffuseColorTexture"].GetInput("sourceColorSpace").Get() == "sRGB"
    varname = shaders["/World/Materials/Bricks/StReader"].GetInput("varname")
    assert varname.GetTypeName() == Sdf.ValueTypeNames.String and varname.Get() == "st"
    # The images exist beside the layer, at the relative paths the layer names.
    for texture in ("normalTexture", "diffuseColorTexture"):
        asset = shaders[f"/World/Materials/Bricks/{texture}"].GetInput("file").Get()
        assert asset.path.startswith("./") and (layer_dir / asset.path).is_file()
        assert Path(asset.resolvedPath) == (layer_dir / asset.path).resolve()
    # Decoded as the layer says, the normal map is unit length and mostly faces out.
    pixels = oiio.ImageBuf(str(layer_dir / "textures/glossy_brick_normal.png")).get_pixels(oiio.FLOAT)
    normals = pixels * 2.0 - 1.0
    assert np.abs(np.linalg.norm(normals, axis=-1) - 1.0).max() < 0.02
    assert np.median(normals[..., 2]) > 0.99
    # Metals and their roughness.
    for name, roughness in (("Gold", 0.2), ("Copper", 0.4), ("Aluminium", 0.7)):
        surface = shaders[f"/World/Materials/{name}/PreviewSurface"]
        assert surface.GetInput("metallic").Get() == 1.0
        assert surface.GetInput("roughness").Get() == pytest.approx(roughness)
    prims = list(stage.Traverse())
    assert any(prim.IsA(UsdGeom.Sphere) for prim in prims) and any(prim.IsA(UsdGeom.Cylinder) for prim in prims)
    copper = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/World/Geometry/CopperSphere"))
    assert copper.HasPrimvar("normals") and copper.HasPrimvar("st")
    spot = stage.GetPrimAtPath(glossy.SPOT)
    assert spot.HasAPI(UsdLux.ShapingAPI) and UsdLux.ShapingAPI(spot).GetShapingConeAngleAttr().Get() == 22.0


def test_glossy_spot_points_at_the_gold_sphere(stages):
    world_from_spot = _world_from_local(stages["glossy"].GetPrimAtPath(glossy.SPOT))
    expected = np.subtract(glossy.GOLD_POSITION, glossy.SPOT_POSITION)
    np.testing.assert_allclose(-world_from_spot[:3, 2], expected / np.linalg.norm(expected), atol=1e-6)


def test_normal_map_of_a_ramp_tilts_against_the_slope():
    # h = 0.25 s on a 64-pixel texture with depth 1: dh/ds = 0.25 -> n = (-0.25, 0, 1) / |.|.
    size = 64
    ramp_s = np.tile(np.arange(size) / size * 0.25, (size, 1))
    ramp_t = ramp_s.T[::-1]  # rows run down, t runs up
    expected_s = np.array([-0.25, 0.0, 1.0]) / np.sqrt(1.0625)
    expected_t = np.array([0.0, -0.25, 1.0]) / np.sqrt(1.0625)
    np.testing.assert_allclose(
        normal_map_from_height(ramp_s, 1.0)[5:-5, 5:-5], np.broadcast_to(expected_s, (54, 54, 3)), atol=1e-6
    )
    np.testing.assert_allclose(
        normal_map_from_height(ramp_t, 1.0)[5:-5, 5:-5], np.broadcast_to(expected_t, (54, 54, 3)), atol=1e-6
    )


def test_brick_height_tiles_and_has_mortar():
    height = brick_height(256, 4, 8)
    assert height.min() == 0.0 and height.max() == 1.0
    # Seamless: the wrap-around neighbours differ no more than interior neighbours.
    assert np.abs(height[:, 0] - height[:, -1]).max() <= np.abs(np.diff(height, axis=1)).max()
    assert np.abs(height[0] - height[-1]).max() <= np.abs(np.diff(height, axis=0)).max()


# ---------------------------------------------------------------------------------------- set


def test_set_has_enough_triangles_and_uses_both_instancing_kinds(stages):
    stage = stages["set"]
    num_triangles = _triangle_count(stage)
    assert num_triangles >= 200_000
    columns = [p for p in stage.Traverse() if p.IsInstance()]
    assert len(columns) == 16 and all(p.GetPrototype() for p in columns)
    assert sum(p.IsA(UsdGeom.PointInstancer) for p in stage.Traverse()) == 2
    # The project's walker expands the same instances to the same count.
    from pipeline.scene import load_scene

    assert load_scene(stage.GetRootLayer().realPath).geometry.positions.shape[0] == num_triangles


def test_set_columns_stand_on_the_floor_under_the_arches(stages):
    stage = stages["set"]
    cache = UsdGeom.BBoxCache(Usd.TimeCode.Default(), [UsdGeom.Tokens.default_])
    column = cache.ComputeWorldBound(stage.GetPrimAtPath("/World/Geometry/Columns/Column_00")).ComputeAlignedRange()
    assert column.GetMin()[1] == pytest.approx(0.0) and column.GetMax()[1] == pytest.approx(set_scene.ARCH_SPRING_Y)
    hall = cache.ComputeWorldBound(stage.GetPrimAtPath("/World/Geometry/Room")).ComputeAlignedRange()
    assert hall.GetMax()[1] == pytest.approx(set_scene.HEIGHT + set_scene.WALL)


# ---------------------------------------------------------------------------------------- meshes


def _signed_volume(mesh: MeshData) -> float:
    """Volume enclosed by a closed mesh (divergence theorem); positive when faces face outwards."""
    starts = np.concatenate([[0], np.cumsum(mesh.face_vertex_counts)[:-1]])
    total = 0.0
    for k in range(1, mesh.face_vertex_counts.max() - 1):  # fan triangle k of every face that has one
        has = mesh.face_vertex_counts > k + 1
        a, b, c = (mesh.points[mesh.face_vertex_indices[starts[has] + i]].astype(np.float64) for i in (0, k, k + 1))
        total += np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0
    return total


@pytest.mark.parametrize(
    "mesh, volume",
    [
        (box((1.0, 2.0, 3.0), (5.0, -1.0, 2.0)), 6.0),
        (uv_sphere(2.0, 96, 48), 4.0 / 3.0 * np.pi * 8.0),
        (torus(3.0, 1.0, 128, 64), 2.0 * np.pi**2 * 3.0),
    ],
)
def test_closed_meshes_face_outwards_and_enclose_their_volume(mesh, volume):
    assert _signed_volume(mesh) == pytest.approx(volume, rel=3e-3)


@pytest.mark.parametrize(
    "mesh",
    [
        box((1.0, 2.0, 3.0)),
        uv_sphere(1.0, 16, 8),
        torus(2.0, 0.5, 24, 12),
        revolve(np.array([[1.0, 2.0], [1.0, 0.0]]), 8),  # a downward profile faces the axis
        set_scene.column_mesh(),
        set_scene.arch_mesh(),
        set_scene.vase_mesh(),
        set_scene.chair_mesh(),
    ],
    ids=["box", "sphere", "torus", "inward_band", "column", "arch", "vase", "chair"],
)
def test_authored_normals_agree_with_the_winding(mesh):
    starts = np.concatenate([[0], np.cumsum(mesh.face_vertex_counts)[:-1]])
    corners = [mesh.face_vertex_indices[starts + i] for i in range(3)]
    p0, p1, p2 = (mesh.points[c].astype(np.float64) for c in corners)
    face_normal = np.cross(p1 - p0, p2 - p0)
    assert np.all(np.linalg.norm(face_normal, axis=1) > 0), "degenerate triangle"
    point_normals = sum(mesh.normals[c] for c in corners)
    assert np.all(np.einsum("ij,ij->i", face_normal, point_normals) > 0)
    np.testing.assert_allclose(np.linalg.norm(mesh.normals, axis=1), 1.0, atol=1e-5)


def test_uv_sphere_triangle_count_has_pole_triangles():
    mesh = uv_sphere(1.0, 32, 16)
    assert mesh.num_triangles == 2 * 32 * 14 + 2 * 32
    np.testing.assert_allclose(np.linalg.norm(mesh.points, axis=1), 1.0, atol=1e-6)


# ---------------------------------------------------------------------------------------- transforms


@pytest.mark.parametrize("direction", [(0, 0, -1), (0, -1, 0), (0, 1, 0), (1, 0, 0), (0.3, -0.8, 0.5), (-2, 1, 3)])
def test_aim_rotation_turns_minus_z_onto_the_direction_without_roll(direction):
    stage = Usd.Stage.CreateInMemory()
    xform = UsdGeom.Xform.Define(stage, "/Aimed")
    place(xform, (1.0, 2.0, 3.0), aim_rotation_xyz(np.array(direction, float)))
    world_from_local = _world_from_local(xform.GetPrim())
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    np.testing.assert_allclose(-world_from_local[:3, 2], d, atol=1e-6)
    assert world_from_local[1, 0] == pytest.approx(0.0, abs=1e-6)  # local +X stays horizontal


# ---------------------------------------------------------------------------------------- light edits


def _compose(scene_layer: Path, edit_text: str) -> Usd.Stage:
    """The scene with the edit as the strongest sublayer of an anonymous root."""
    edit = Sdf.Layer.CreateAnonymous(".usda")
    edit.ImportFromString(edit_text)
    root = Sdf.Layer.CreateAnonymous(".usda")
    root.subLayerPaths.append(edit.identifier)
    root.subLayerPaths.append(str(scene_layer))
    return Usd.Stage.Open(root)


@pytest.mark.parametrize("name", sorted(SCENES))
def test_light_edits_compose_over_the_scene(name, written, stages):
    edits = example_light_edits(name)
    assert len(edits) >= 3
    for edit, (edit_name, text) in zip(SCENES[name].light_edits, edits, strict=True):
        assert edit.name == edit_name
        composed = _compose(written[name], text)
        for override in edit.overrides:
            prim = composed.GetPrimAtPath(override.prim_path)
            original = stages[name].GetPrimAtPath(override.prim_path)
            assert prim.GetTypeName() == original.GetTypeName() and prim.HasAPI(UsdLux.LightAPI)
            for api in override.api_schemas:
                assert api in prim.GetAppliedSchemas()
            for attribute, (_, value) in override.values.items():
                assert prim.GetAttribute(attribute).Get() == pytest.approx(value), (edit_name, attribute)
                assert original.GetAttribute(attribute).Get() != pytest.approx(value), "edit changes nothing"


def test_reaim_edit_points_the_glossy_spot_at_the_torus(written):
    text = dict(example_light_edits("glossy"))["reaim_spot"]
    composed = _compose(written["glossy"], text)
    world_from_spot = _world_from_local(composed.GetPrimAtPath(glossy.SPOT))
    torus_center = np.array(
        UsdGeom.Xformable(composed.GetPrimAtPath("/World/Geometry/AluminiumTorus"))
        .ComputeLocalToWorldTransform(Usd.TimeCode.Default())
        .ExtractTranslation()
    )
    expected = torus_center - world_from_spot[:3, 3]
    np.testing.assert_allclose(-world_from_spot[:3, 2], expected / np.linalg.norm(expected), atol=1e-6)


def test_write_light_edits_writes_layers_beside_the_scene(tmp_path):
    paths = write_light_edits("cornell_box", tmp_path)
    assert [p.name for p in paths] == [f"cornell_box.lights.{e.name}.usda" for e in cornell_box.LIGHT_EDITS]
    assert all(Sdf.Layer.FindOrOpen(str(p)) for p in paths)


# ---------------------------------------------------------------------------------------- CLI


def _run_scenes_command(argv: list[str]) -> int:
    """Parse and run `relight scenes ...` through this subcommand alone (independent of the others)."""
    parser = argparse.ArgumentParser(prog="relight")
    scenes_command.add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["scenes", *argv])
    return args.run(args)


def test_cli_lists_and_writes(tmp_path, capsys):
    assert "scenes" in COMMANDS
    assert _run_scenes_command(["list"]) == 0
    listed = capsys.readouterr().out.splitlines()
    assert [line.split()[:2] for line in listed] == [[name, scene.camera] for name, scene in SCENES.items()] + [
        [name, SCENES[layered.base].camera] for name, layered in LAYERED_SCENES.items()
    ]
    assert _run_scenes_command(["write", str(tmp_path), "--name", "cornell_box"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["cornell_box.usda"] + [f"cornell_box.lights.{e.name}.usda" for e in cornell_box.LIGHT_EDITS]
    )
    capsys.readouterr()
    assert _run_scenes_command(["write", str(tmp_path / "layered"), "--name", "glossy+dome"]) == 0
    written = capsys.readouterr().out.splitlines()
    assert written[0].endswith("glossy.usda --lights " + str(tmp_path / "layered" / "glossy.lights.dome.usda"))
    assert len(written) == 1 + len(dome.GLOSSY_DOME.light_edits)
    (tmp_path / "a_file").write_text("")
    with pytest.raises(RelightError, match="a_file"):
        _run_scenes_command(["write", str(tmp_path / "a_file")])


# ------------------------------------------------------------------------------- layered scenes


def test_glossy_dome_layer_adds_the_dome_and_keeps_the_shots_lights(tmp_path):
    layers = layered_edit_layers("glossy+dome", tmp_path)
    assert list(layers) == ["shot", *(edit.name for edit in dome.GLOSSY_DOME.light_edits)]
    shot = tmp_path / "glossy.usda"
    lights = {light.path: light for light in load_scene(shot, lights_layer=layers["shot"], width=8, height=6).lights}
    assert {path: light.kind for path, light in lights.items()} == {
        glossy.KEY: LightKind.SPHERE,
        glossy.SPOT: LightKind.SPHERE,
        dome.DOME: LightKind.DOME,
    }
    assert lights[dome.DOME].intensity == pytest.approx(dome.FILL_INTENSITY)
    np.testing.assert_allclose(lights[dome.DOME].texture, dome.sky_texture(), rtol=1e-3, atol=1e-3)
    # The layer only adds: the shot's Lights prim keeps its type, the shot's file is glossy's own.
    composed = Usd.Stage.Open(str(shot))
    composed.GetRootLayer().subLayerPaths.insert(0, str(layers["shot"]))
    assert composed.GetPrimAtPath("/World/Lights").GetTypeName() == "Xform"
    assert shot.read_text() == glossy.write(tmp_path / "plain").read_text()


def test_glossy_dome_edits_go_over_its_layer(tmp_path):
    layers = layered_edit_layers("glossy+dome", tmp_path)
    shot = tmp_path / "glossy.usda"
    before = {light.path: light for light in load_scene(shot, lights_layer=layers["shot"], width=8, height=6).lights}
    after = {light.path: light for light in load_scene(shot, lights_layer=layers["rotate"], width=8, height=6).lights}
    turn = np.radians(120.0)
    about_y = np.array([[np.cos(turn), 0, np.sin(turn)], [0, 1, 0], [-np.sin(turn), 0, np.cos(turn)]])
    np.testing.assert_allclose(after[dome.DOME].world_from_light[:3, :3], about_y, atol=1e-6)
    np.testing.assert_allclose(before[dome.DOME].world_from_light[:3, :3], np.eye(3), atol=1e-6)
    np.testing.assert_array_equal(after[glossy.KEY].world_from_light, before[glossy.KEY].world_from_light)
    moved = {light.path: light for light in load_scene(shot, lights_layer=layers["move"], width=8, height=6).lights}
    assert dome.DOME in moved and not np.allclose(
        moved[glossy.KEY].world_from_light, before[glossy.KEY].world_from_light
    )
    added = new_sphere_layer(shot, glossy.CAMERA, tmp_path / "new.usda", over=layers["shot"])
    paths = {light.path for light in load_scene(shot, lights_layer=added, width=8, height=6).lights}
    assert paths == {glossy.KEY, glossy.SPOT, dome.DOME, NEW_LIGHT_PATH}


def test_unknown_layered_scene_is_one_error(tmp_path):
    with pytest.raises(RelightError, match=r"unknown layered scene 'glossy\+sky'"):
        layered_edit_layers("glossy+sky", tmp_path)
