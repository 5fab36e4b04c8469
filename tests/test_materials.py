"""MaterialLibrary: UsdPreviewSurface networks read from small authored stages."""

import numpy as np
import OpenImageIO as oiio
import pytest
from pxr import Gf, Sdf, Usd, UsdShade

from pipeline.errors import RelightError
from pipeline.scene.materials import MaterialLibrary
from pipeline.scene.surface import evaluate_materials


def write_exr(path, pixels):
    """(H, W, C) float32 pixels, row 0 = top."""
    height, width, num_channels = pixels.shape
    output = oiio.ImageOutput.create(str(path))
    output.open(str(path), oiio.ImageSpec(width, height, num_channels, "float"))
    output.write_image(np.asarray(pixels, np.float32))
    output.close()


def new_stage(tmp_path):
    return Usd.Stage.CreateNew(str(tmp_path / "shot.usda"))


def preview_material(stage, path):
    """A Material with a UsdPreviewSurface 'Surface' child wired to its surface output."""
    material = UsdShade.Material.Define(stage, path)
    shader = UsdShade.Shader.Define(stage, f"{path}/Surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    return material, shader


def uv_texture(stage, path, file, st_source=None):
    """A UsdUVTexture reading `file`, its st from a primvar reader of 'st' unless `st_source`."""
    texture = UsdShade.Shader.Define(stage, path)
    texture.CreateIdAttr("UsdUVTexture")
    texture.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(file)
    if st_source is None:
        reader = UsdShade.Shader.Define(stage, f"{path}_st")
        reader.CreateIdAttr("UsdPrimvarReader_float2")
        reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
        st_source = reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)
    texture.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(st_source)
    return texture


def library_for(stage):
    warnings = []
    return MaterialLibrary(stage, warnings), warnings


def test_constant_inputs(tmp_path):
    stage = new_stage(tmp_path)
    material, shader = preview_material(stage, "/Looks/Gold")
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0.9, 0.6, 0.2))
    shader.CreateInput("emissiveColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0.0, 0.1, 0.0))
    shader.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(1)
    shader.CreateInput("specularColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0.3, 0.3, 0.4))
    shader.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.75)
    shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.25)
    shader.CreateInput("clearcoat", Sdf.ValueTypeNames.Float).Set(0.5)
    shader.CreateInput("clearcoatRoughness", Sdf.ValueTypeNames.Float).Set(0.1)
    shader.CreateInput("opacity", Sdf.ValueTypeNames.Float).Set(0.6)
    shader.CreateInput("opacityThreshold", Sdf.ValueTypeNames.Float).Set(0.4)
    shader.CreateInput("opacityMode", Sdf.ValueTypeNames.Token).Set("presence")
    shader.CreateInput("ior", Sdf.ValueTypeNames.Float).Set(1.33)
    library, warnings = library_for(stage)
    index = library.id_for(material, np.array([0.1, 0.2, 0.3]), "/Geo/Ball")
    record = library.materials[index]
    assert record.path == "/Looks/Gold" and warnings == []
    np.testing.assert_allclose(record.diffuse_color.value, [0.9, 0.6, 0.2], rtol=1e-6)
    np.testing.assert_allclose(record.emissive_color.value, [0.0, 0.1, 0.0], rtol=1e-6)
    np.testing.assert_allclose(record.specular_color.value, [0.3, 0.3, 0.4], rtol=1e-6)
    scalars = ["metallic", "roughness", "clearcoat", "clearcoat_roughness", "opacity", "ior"]
    np.testing.assert_allclose(
        [getattr(record, name).value[0] for name in scalars], [0.75, 0.25, 0.5, 0.1, 0.6, 1.33], rtol=1e-6
    )
    assert record.use_specular_workflow is True
    assert (record.opacity_threshold, record.opacity_mode) == (pytest.approx(0.4), "presence")
    # Unauthored inputs keep the 26.11 registered fallbacks.
    np.testing.assert_allclose(record.normal.value, [0.0, 0.0, 1.0])


def test_same_material_is_read_once_and_shared(tmp_path):
    stage = new_stage(tmp_path)
    material, _ = preview_material(stage, "/Looks/Plain")
    library, _ = library_for(stage)
    first = library.id_for(material, np.array([1.0, 0.0, 0.0]), "/A")
    second = library.id_for(UsdShade.Material(stage.GetPrimAtPath("/Looks/Plain")), None, "/B")
    assert first == second and len(library.materials) == 1


def test_display_color_and_fallback_materials(tmp_path):
    library, warnings = library_for(new_stage(tmp_path))
    red = library.id_for(None, np.array([1.0, 0.0, 0.0]), "/A")
    also_red = library.id_for(None, np.array([1.0, 0.0, 0.0]), "/B")
    blue = library.id_for(None, np.array([0.0, 0.0, 1.0]), "/C")
    grey = library.id_for(UsdShade.Material(), None, "/D")
    assert red == also_red and len({red, blue, grey}) == 3
    assert library.materials[red].path == "<displayColor>"
    np.testing.assert_allclose(library.materials[blue].diffuse_color.value, [0.0, 0.0, 1.0])
    assert library.materials[grey].path == "<fallback>"
    np.testing.assert_allclose(library.materials[grey].diffuse_color.value, [0.18, 0.18, 0.18], rtol=1e-6)
    assert warnings == []
    with pytest.raises(RelightError, match="/E"):
        library.id_for(None, np.array([np.nan, 0.0, 0.0]), "/E")


def test_display_color_primvar_reader_gives_one_material_per_colour(tmp_path):
    stage = new_stage(tmp_path)
    material, shader = preview_material(stage, "/Looks/Ceramic")
    reader = UsdShade.Shader.Define(stage, "/Looks/Ceramic/DisplayColor")
    reader.CreateIdAttr("UsdPrimvarReader_float3")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("displayColor")
    reader.CreateInput("fallback", Sdf.ValueTypeNames.Float3).Set(Gf.Vec3f(0.5, 0.5, 0.5))
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        reader.CreateOutput("result", Sdf.ValueTypeNames.Float3)
    )
    shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.125)
    library, warnings = library_for(stage)
    green = library.id_for(material, np.array([0.3, 0.8, 0.0]), "/A")
    orange = library.id_for(material, np.array([0.9, 0.4, 0.0]), "/B")
    no_colour = library.id_for(material, None, "/C")
    assert len({green, orange, no_colour}) == 3 and warnings == []
    np.testing.assert_allclose(library.materials[green].diffuse_color.value, [0.3, 0.8, 0.0], rtol=1e-6)
    np.testing.assert_allclose(library.materials[orange].roughness.value, [0.125])
    np.testing.assert_allclose(library.materials[no_colour].diffuse_color.value, [0.5, 0.5, 0.5])


def test_unknown_shader_warns_once_and_is_grey(tmp_path):
    stage = new_stage(tmp_path)
    material = UsdShade.Material.Define(stage, "/Looks/Arnold")
    shader = UsdShade.Shader.Define(stage, "/Looks/Arnold/Surface")
    shader.CreateIdAttr("arnold:standard_surface")
    shader.CreateInput("base_color", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(1, 0, 0))
    material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    library, warnings = library_for(stage)
    first = library.id_for(material, None, "/A")
    second = library.id_for(material, np.array([0.0, 1.0, 0.0]), "/B")
    assert first == second
    assert len(warnings) == 1 and "/Looks/Arnold" in warnings[0] and "arnold:standard_surface" in warnings[0]
    np.testing.assert_allclose(library.materials[first].diffuse_color.value, [0.18, 0.18, 0.18], rtol=1e-6)


def test_texture_connection_evaluates_to_texels(tmp_path):
    # 2 x 2 image, row 0 = top: roughness 0.1 0.2 / 0.3 0.4 in the red channel, green = 1 - red.
    red = np.array([[0.1, 0.2], [0.3, 0.4]], np.float32)
    write_exr(tmp_path / "rough.exr", np.stack([red, 1 - red, np.zeros_like(red)], axis=-1))
    stage = new_stage(tmp_path)
    material, shader = preview_material(stage, "/Looks/Rough")
    texture = uv_texture(stage, "/Looks/Rough/Tex", "./rough.exr")
    texture.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("clamp")
    texture.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(2, 1, 1, 1))
    texture.CreateInput("bias", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(0.05, 0, 0, 0))
    shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).ConnectToSource(
        texture.CreateOutput("r", Sdf.ValueTypeNames.Float)
    )
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        texture.CreateOutput("g", Sdf.ValueTypeNames.Float)
    )
    stage.Save()
    library, warnings = library_for(stage)
    index = library.id_for(material, None, "/A")
    record = library.materials[index]
    assert warnings == [] and record.roughness.texture.output == "r"
    assert (record.roughness.texture.wrap_s, record.roughness.texture.wrap_t) == ("clamp", "black")
    # Texel centres: lower-left (0.25, 0.25) is 0.3, upper-right (0.75, 0.75) is 0.2.
    uvs = np.array([[0.25, 0.25], [0.75, 0.75]], np.float32)
    params = evaluate_materials(library.materials, np.full(2, index, np.int32), uvs)
    np.testing.assert_allclose(params["roughness"], [0.3 * 2 + 0.05, 0.2 * 2 + 0.05], rtol=1e-6)
    # A one-channel output feeding a colour is broadcast to grey.
    np.testing.assert_allclose(params["diffuse_color"], [[0.7] * 3, [0.8] * 3], rtol=1e-6)


def test_nodegraph_and_interface_connections(tmp_path):
    write_exr(tmp_path / "albedo.exr", np.full((1, 1, 3), 0.25, np.float32))
    stage = new_stage(tmp_path)
    material = UsdShade.Material.Define(stage, "/Looks/Wrapped")
    material.CreateInput("tint_file", Sdf.ValueTypeNames.Asset).Set("./albedo.exr")
    material.CreateInput("gloss", Sdf.ValueTypeNames.Float).Set(0.35)
    graph = UsdShade.NodeGraph.Define(stage, "/Looks/Wrapped/Graph")
    graph.CreateInput("gloss", Sdf.ValueTypeNames.Float).ConnectToSource(material.GetInput("gloss"))
    shader = UsdShade.Shader.Define(stage, "/Looks/Wrapped/Graph/Surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).ConnectToSource(graph.GetInput("gloss"))
    texture = uv_texture(stage, "/Looks/Wrapped/Graph/Tex", "./does_not_exist.exr")
    texture.GetInput("file").ConnectToSource(material.GetInput("tint_file"))
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        texture.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    )
    surface = shader.CreateOutput("surface", Sdf.ValueTypeNames.Token)
    graph.CreateOutput("surface", Sdf.ValueTypeNames.Token).ConnectToSource(surface)
    material.CreateSurfaceOutput().ConnectToSource(graph.GetOutput("surface"))
    stage.Save()
    library, warnings = library_for(stage)
    record = library.materials[library.id_for(material, None, "/A")]
    assert warnings == []
    np.testing.assert_allclose(record.roughness.value, [0.35], rtol=1e-6)
    assert record.diffuse_color.texture.file.endswith("albedo.exr")


def test_missing_texture_warns_and_uses_fallbacks(tmp_path):
    stage = new_stage(tmp_path)
    material, shader = preview_material(stage, "/Looks/Lost")
    with_fallback = uv_texture(stage, "/Looks/Lost/TexA", "./missing_a.png")
    with_fallback.CreateInput("fallback", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(0.0, 0.0, 1.0, 0.5))
    without_fallback = uv_texture(stage, "/Looks/Lost/TexB", "./missing_b.png")
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        with_fallback.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    )
    shader.CreateInput("opacity", Sdf.ValueTypeNames.Float).ConnectToSource(
        with_fallback.CreateOutput("a", Sdf.ValueTypeNames.Float)
    )
    roughness = shader.CreateInput("roughness", Sdf.ValueTypeNames.Float)
    roughness.Set(0.7)
    roughness.ConnectToSource(without_fallback.CreateOutput("g", Sdf.ValueTypeNames.Float))
    stage.Save()
    library, warnings = library_for(stage)
    record = library.materials[library.id_for(material, None, "/A")]
    np.testing.assert_allclose(record.diffuse_color.value, [0.0, 0.0, 1.0])
    np.testing.assert_allclose(record.opacity.value, [0.5])
    np.testing.assert_allclose(record.roughness.value, [0.7], rtol=1e-6)
    assert record.diffuse_color.texture is None and record.roughness.texture is None
    assert any("missing_a.png" in w and "/Looks/Lost" in w for w in warnings)
    assert any("missing_b.png" in w and "/Looks/Lost" in w for w in warnings)


def test_corrupt_texture_warns_and_uses_the_shader_value(tmp_path):
    (tmp_path / "broken.png").write_bytes(b"not an image at all" * 4)
    stage = new_stage(tmp_path)
    material, shader = preview_material(stage, "/Looks/Broken")
    texture = uv_texture(stage, "/Looks/Broken/Tex", "./broken.png")
    diffuse = shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f)
    diffuse.Set(Gf.Vec3f(0.2, 0.4, 0.6))
    diffuse.ConnectToSource(texture.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))
    stage.Save()
    library, warnings = library_for(stage)
    record = library.materials[library.id_for(material, None, "/A")]
    np.testing.assert_allclose(record.diffuse_color.value, [0.2, 0.4, 0.6], rtol=1e-6)
    assert len(warnings) == 1 and "broken.png" in warnings[0] and "/Looks/Broken" in warnings[0]


def test_transform2d_chain_and_token_varname(tmp_path):
    write_exr(tmp_path / "t.exr", np.ones((2, 2, 3), np.float32))
    stage = new_stage(tmp_path)
    material, shader = preview_material(stage, "/Looks/Moved")
    reader = UsdShade.Shader.Define(stage, "/Looks/Moved/Reader")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set("st")  # token: tolerated
    inner = UsdShade.Shader.Define(stage, "/Looks/Moved/Scale")
    inner.CreateIdAttr("UsdTransform2d")
    uv = reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)
    inner.CreateInput("in", Sdf.ValueTypeNames.Float2).ConnectToSource(uv)
    inner.CreateInput("scale", Sdf.ValueTypeNames.Float2).Set(Gf.Vec2f(2.0, 3.0))
    outer = UsdShade.Shader.Define(stage, "/Looks/Moved/Rotate")
    outer.CreateIdAttr("UsdTransform2d")
    scaled = inner.CreateOutput("result", Sdf.ValueTypeNames.Float2)
    outer.CreateInput("in", Sdf.ValueTypeNames.Float2).ConnectToSource(scaled)
    outer.CreateInput("rotation", Sdf.ValueTypeNames.Float).Set(90.0)
    outer.CreateInput("translation", Sdf.ValueTypeNames.Float2).Set(Gf.Vec2f(0.5, 0.25))
    texture = uv_texture(stage, "/Looks/Moved/Tex", "./t.exr", outer.CreateOutput("result", Sdf.ValueTypeNames.Float2))
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        texture.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    )
    stage.Save()
    library, warnings = library_for(stage)
    st_from_uv = library.materials[library.id_for(material, None, "/A")].diffuse_color.texture.st_from_uv
    # uv (1, 1) -> scaled (2, 3) -> rotated 90 deg CCW (-3, 2) -> translated (-2.5, 2.25).
    np.testing.assert_allclose(st_from_uv @ [1.0, 1.0, 1.0], [-2.5, 2.25, 1.0], atol=1e-6)
    assert warnings == []
