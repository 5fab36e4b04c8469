"""Textures packed inside a .usdz are read from the package (through Ar), with the same pixels
as the unpacked files, and errors name the package path."""

from __future__ import annotations

import numpy as np
import OpenImageIO as oiio
import pytest
from pxr import Sdf, Usd, UsdGeom, UsdLux, UsdShade, UsdUtils

from pipeline.errors import RelightError
from pipeline.scene import load_scene
from pipeline.scene.textures import read_packaged_image


def _write_png(path, pixels: np.ndarray) -> None:
    """(H, W, 3) uint8 pixels, row 0 = top."""
    path.parent.mkdir(parents=True, exist_ok=True)
    height, width, channels = pixels.shape
    output = oiio.ImageOutput.create(str(path))
    output.open(str(path), oiio.ImageSpec(width, height, channels, "uint8"))
    output.write_image(pixels)
    output.close()


def _textured_plane(directory, texture: str = "textures/checker.png"):
    """A shot: a unit quad (st primvar) whose diffuse colour reads `texture`, a camera, a light."""
    path = directory / "plane.usda"
    stage = Usd.Stage.CreateNew(str(path))
    mesh = UsdGeom.Mesh.Define(stage, "/World/Plane")
    mesh.CreatePointsAttr([(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mesh.CreateSubdivisionSchemeAttr("none")
    st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
    st.Set([(0, 0), (1, 0), (1, 1), (0, 1)])
    material = UsdShade.Material.Define(stage, "/World/Look")
    surface = UsdShade.Shader.Define(stage, "/World/Look/Surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    reader = UsdShade.Shader.Define(stage, "/World/Look/St")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set("st")
    image = UsdShade.Shader.Define(stage, "/World/Look/Image")
    image.CreateIdAttr("UsdUVTexture")
    image.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(texture)
    image.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(image.ConnectableAPI(), "rgb")
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
    camera = UsdGeom.Camera.Define(stage, "/World/Cam")
    camera.AddTranslateOp().Set((0, 0, 5))
    UsdLux.SphereLight.Define(stage, "/World/Key").AddTranslateOp().Set((0, 0, 3))
    stage.Save()
    return path


def _diffuse_texture(scene):
    (material,) = [m for m in scene.materials if m.path == "/World/Look"]
    return material.diffuse_color.texture


def test_texture_inside_usdz_matches_the_unpacked_file(tmp_path):
    pixels = np.random.default_rng(5).integers(0, 256, (8, 16, 3), dtype=np.uint8)
    _write_png(tmp_path / "textures" / "checker.png", pixels)
    source = _textured_plane(tmp_path)
    package = tmp_path / "packed" / "plane.usdz"
    package.parent.mkdir()
    assert UsdUtils.CreateNewUsdzPackage(str(source), str(package))

    unpacked = load_scene(source)
    packed = load_scene(package)
    assert not [w for w in packed.warnings if "texture" in w or "image" in w]
    texture = _diffuse_texture(packed)
    assert texture is not None
    assert texture.file.startswith(str(package)) and texture.file.endswith("checker.png]")
    np.testing.assert_array_equal(texture.pixels, _diffuse_texture(unpacked).pixels)
    assert texture.pixels.shape == (8, 16, 3)


def test_corrupt_packaged_texture_warns_with_the_package_path(tmp_path):
    bad = tmp_path / "textures" / "broken.png"
    bad.parent.mkdir()
    bad.write_bytes(b"not an image at all")
    package = tmp_path / "plane.usdz"
    assert UsdUtils.CreateNewUsdzPackage(str(_textured_plane(tmp_path, "textures/broken.png")), str(package))
    scene = load_scene(package)
    assert _diffuse_texture(scene) is None
    (warning,) = [w for w in scene.warnings if "broken.png" in w]
    assert f"{package}[" in warning and "relight-package-" not in warning


def test_missing_packaged_file_is_an_error_naming_it(tmp_path):
    pixels = np.zeros((2, 2, 3), np.uint8)
    _write_png(tmp_path / "textures" / "checker.png", pixels)
    package = tmp_path / "plane.usdz"
    assert UsdUtils.CreateNewUsdzPackage(str(_textured_plane(tmp_path)), str(package))
    missing = f"{package}[textures/nope.png]"
    with pytest.raises(RelightError, match=r"nope\.png"):
        read_packaged_image(missing)
