"""MaterialLibrary on OpenUSD's own UsdPreviewSurface test scenes (tests/data/materials/PROVENANCE.md)."""

from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdGeom, UsdShade

from pipeline.scene.materials import MaterialLibrary
from pipeline.scene.surface import evaluate_materials, shading_frame
from relight_torch.io.images import read_image, srgb_to_linear

DATA = Path(__file__).parent / "data" / "materials"


def load(name, purpose=UsdShade.Tokens.allPurpose):
    """Bind every gprim of a test scene the way the walker does; returns (library, warnings, ids by prim)."""
    stage = Usd.Stage.Open(str(DATA / f"{name}.usda"))
    warnings = []
    library = MaterialLibrary(stage, warnings)
    ids = {}
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.Gprim):
            continue
        material, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial(purpose)
        colors = UsdGeom.Gprim(prim).GetDisplayColorAttr().Get()
        path = str(prim.GetPath())
        ids[path] = library.id_for(material, np.array(colors[0]) if colors else None, path)
    return library, warnings, ids


def by_path(library, path):
    return next(i for i, m in enumerate(library.materials) if m.path == path)


def texel_centres(size):
    coordinates = (np.arange(size) + 0.5) / size
    u, v = np.meshgrid(coordinates, coordinates)
    return np.stack([u.ravel(), v.ravel()], axis=-1).astype(np.float32)


def evaluate(library, material_index, uvs, key="diffuse_color"):
    return evaluate_materials(library.materials, np.full(len(uvs), material_index, np.int32), uvs)[key]


def test_texture_file_from_material_interface():
    library, warnings, ids = load("testPreviewSurfaceTexture")
    material = library.materials[ids["/Scene/Geom/Plane"]]
    assert warnings == []
    # The file input is connected to the Material's interface (grid.png); its own value grid_1.png is ignored.
    assert Path(material.diffuse_color.texture.file).name == "grid.png"
    np.testing.assert_allclose(material.roughness.value, [0.8], rtol=1e-6)
    # grid.png is 8-bit RGBA, so 'auto' decodes sRGB; the top-left texel sits at st (0.5/512, 1 - 0.5/512).
    encoded = read_image(str(DATA / "grid.png"), "raw").pixels
    top_left = evaluate(library, ids["/Scene/Geom/Plane"], np.array([[0.5 / 512, 1 - 0.5 / 512]], np.float32))
    np.testing.assert_allclose(top_left[0], srgb_to_linear(encoded[0, 0, :3]), rtol=1e-5)


def test_source_color_space_srgb_matches_linear_twin():
    # texLinear.png stores linear values, texSRGB.png the same picture sRGB-encoded.
    library, warnings, ids = load("testPreviewSurfaceSourceColorSpace")
    uvs = texel_centres(256)
    linear = evaluate(library, ids["/Scene/Geom/Plane1"], uvs)
    decoded = evaluate(library, ids["/Scene/Geom/Plane2"], uvs)
    assert warnings == []
    assert np.mean(np.abs(decoded - linear)) < 0.005  # 8-bit quantisation of the linear file
    # Read without decoding, the two files differ by 0.18 on average.
    encoded = read_image(str(DATA / "texSRGB.png"), "raw").pixels
    assert np.mean(np.abs(encoded - read_image(str(DATA / "texLinear.png"), "raw").pixels)) > 0.1


def test_texture_scale_and_bias():
    library, warnings, _ = load("testPreviewSurfaceTextureScaleAndBias")
    uvs = np.random.default_rng(7).random((500, 2), dtype=np.float32)
    plain, scaled, biased, both = (
        evaluate(library, by_path(library, f"/Scene/Looks/Material{k}"), uvs) for k in (1, 2, 3, 4)
    )
    assert warnings == []
    np.testing.assert_allclose(scaled, plain * [1.0, 0.2, 1.0], rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(biased, plain + [0.2, 0.0, 0.2], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(both, plain * [1.0, 0.2, 1.0] + [0.2, 0.0, 0.2], rtol=1e-5, atol=1e-6)


def test_material_interface_inputs():
    library, warnings, ids = load("testPreviewSurfaceMaterialInterface")
    material = library.materials[ids["/Scene/Geom/Sphere"]]
    np.testing.assert_allclose(material.roughness.value, [0.3], rtol=1e-6)
    # diffuseColor reads primvar 'mydisplayColor', which is not baked: the authored constant, one warning.
    np.testing.assert_allclose(material.diffuse_color.value, [1.0, 0.0, 0.0])
    assert len(warnings) == 1 and "mydisplayColor" in warnings[0] and "/Scene/Looks/Material" in warnings[0]


def test_texture_without_file_uses_its_fallback():
    library, warnings, ids = load("testPreviewSurfaceTextureNoFile", UsdShade.Tokens.preview)
    material = library.materials[ids["/Scene/Geom/Plane"]]
    assert material.path == "/Scene/Looks/MainMaterial" and material.diffuse_color.texture is None
    np.testing.assert_allclose(material.diffuse_color.value, [0.0, 0.0, 1.0])  # float3 fallback
    assert len(warnings) == 1 and "no file" in warnings[0] and "/Scene/Looks/MainMaterial" in warnings[0]


def test_missing_texture_file_uses_its_fallback():
    library, warnings, ids = load("testPreviewSurfaceTextureFallback", UsdShade.Tokens.preview)
    material = library.materials[ids["/Scene/Geom/Plane"]]
    np.testing.assert_allclose(material.diffuse_color.value, [0.0, 0.0, 1.0])
    assert len(warnings) == 1
    assert "somethingWrong.jpg" in warnings[0] and "/Scene/Looks/MainMaterial" in warnings[0]


def test_transform2d():
    library, warnings, _ = load("testPreviewSurfaceTransform2d")
    textures = [
        library.materials[by_path(library, f"/Scene/Looks/Material{k}")].diffuse_color.texture for k in range(1, 5)
    ]
    assert warnings == []
    np.testing.assert_allclose(textures[0].st_from_uv, np.eye(3))
    # Material2: rotate 45 deg CCW, translate (0.5, -0.2): uv (1, 0) -> (cos 45 + 0.5, sin 45 - 0.2).
    root_half = np.sqrt(0.5)
    np.testing.assert_allclose(textures[1].st_from_uv @ [1, 0, 1], [root_half + 0.5, root_half - 0.2, 1], atol=1e-6)
    # Material4: scale 2, rotate -90, translate (0, 1): uv (1, 0) -> (2, 0) -> (0, -2) -> (0, -1).
    np.testing.assert_allclose(textures[3].st_from_uv @ [1, 0, 1], [0, -1, 1], atol=1e-6)
    # Material3 (scale (0.5, 1)) at uv (0.5, 0.5) shows what Material1 shows at (0.25, 0.5).
    halved = evaluate(library, by_path(library, "/Scene/Looks/Material3"), np.array([[0.5, 0.5]], np.float32))
    plain = evaluate(library, by_path(library, "/Scene/Looks/Material1"), np.array([[0.25, 0.5]], np.float32))
    np.testing.assert_allclose(halved, plain, rtol=1e-6)


def test_normal_map_decodes_to_unit_tangent_space_normals():
    library, warnings, ids = load("testPreviewSurfaceNormalMap")
    assert warnings == [] and len(set(ids.values())) == 1
    normal_tangent = evaluate(library, ids["/Scene/Geom/Plane1"], texel_centres(256), "normal_tangent")
    # raw 8-bit values * 2 - 1: close to unit length, mostly facing +z (mean blue 0.977 -> z 0.953).
    assert np.median(np.abs(np.linalg.norm(normal_tangent, axis=-1) - 1)) < 0.01
    assert normal_tangent[:, 2].mean() == pytest.approx(0.953, abs=0.005)
    num_points = len(normal_tangent)
    _, _, n = shading_frame(
        np.tile([0.0, 0.0, 1.0], (num_points, 1)), np.tile([1.0, 0.0, 0.0], (num_points, 1)), normal_tangent
    )
    np.testing.assert_allclose(n, normal_tangent / np.linalg.norm(normal_tangent, axis=-1, keepdims=True), atol=1e-6)
