"""MaterialX materials: the composition-error policy, the surface mappings, image nodes, and direct
relighting of MaterialX's own example materials against the reference.

tests/data/materialx/ holds example materials copied from the MaterialX repository
(PROVENANCE.md) and shot.usda, which references them from USD (most through a material variant)
and authors two MaterialX networks directly in UsdShade.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.bake.direct.bake import bake_direct
from pipeline.bake.inputs import input_files
from pipeline.cli import main
from pipeline.errors import RelightError
from pipeline.reference.path_tracer import PathTracer, ReferenceSettings
from pipeline.scene import find_camera, load_scene
from pipeline.scene.materialx_graph import channel_mean, scaled
from pipeline.scene.surface import evaluate_materials
from pipeline.scene.textures import sample_texture, select_output
from pipeline.scene.types import MaterialInput, Texture
from relight_torch.direct.relighter import Relighter
from relight_torch.io.exr import write_rgb_exr
from relight_torch.metrics import psnr

DATA = Path(__file__).parent / "data" / "materialx"
SHOT = DATA / "shot.usda"
LOOKS = (
    "Wood",
    "Gold",
    "Copper",
    "CarPaint",
    "OpenPbrCarPaint",
    "Pearl",
    "Aluminum",
    "Plastic",
    "UsdStandardSurface",
    "UsdOpenPbr",
)

# A wall bound to a material whose variant references a .mtlx document, and optionally a prim that
# references geometry from another file.
STAGE = """#usda 1.0
(
    upAxis = "Y"
    metersPerUnit = 1
)
def Xform "World"
{{
    def Mesh "Wall" (
        prepend apiSchemas = ["MaterialBindingAPI"]
    )
    {{
        int[] faceVertexCounts = [4]
        int[] faceVertexIndices = [0, 1, 2, 3]
        point3f[] points = [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)]
        texCoord2f[] primvars:st = [(0, 0), (1, 0), (1, 1), (0, 1)] (interpolation = "vertex")
        rel material:binding = </World/Looks/Paint>
    }}
    def Camera "Camera"
    {{
        double3 xformOp:translate = (0, 0, 4)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }}
    def SphereLight "Key"
    {{
        float inputs:intensity = 10
        double3 xformOp:translate = (0, 0, 3)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }}
    def Scope "Looks"
    {{
        def Material "Paint" (
            variants = {{
                string look = "mtlx"
            }}
            prepend variantSets = "look"
        )
        {{
            variantSet "look" = {{
                "mtlx" (
                    references = @./{document}@</MaterialX/Materials/{material}>
                ) {{
                }}
            }}
        }}
    }}{extra}
}}
"""
PROP = """
    def Xform "Prop" (
        references = @./prop.usda@
    )
    {
    }"""


def _stage(directory: Path, document: str, material: str = "Gold", extra: str = "") -> Path:
    shot = directory / "shot.usda"
    shot.write_text(STAGE.format(document=document, material=material, extra=extra))
    return shot


def _by_path(scene, name):
    return next(material for material in scene.materials if material.path == f"/World/Looks/{name}")


@pytest.fixture(scope="module")
def scene():
    return load_scene(SHOT, width=64, height=48)


# The composition-error policy -----------------------------------------------------------------


def test_mtlx_reference_in_a_variant_no_longer_fails_the_stage(tmp_path):
    shutil.copy(DATA / "standard_surface_gold.mtlx", tmp_path)
    scene = load_scene(_stage(tmp_path, "standard_surface_gold.mtlx"))
    paint = _by_path(scene, "Paint")
    np.testing.assert_allclose(paint.diffuse_color.value, [0.944, 0.776, 0.373], rtol=1e-6)
    assert not [message for message in scene.warnings if "Paint" in message]


def test_missing_mtlx_document_is_a_warning_naming_the_material_and_the_fallback(tmp_path):
    scene = load_scene(_stage(tmp_path, "nowhere.mtlx"))
    paint = _by_path(scene, "Paint")
    assert paint.diffuse_color.value.tolist() == pytest.approx([0.18] * 3)
    (message,) = [message for message in scene.warnings if "/World/Looks/Paint" in message]
    assert "nowhere.mtlx not found" in message and "using grey 0.18 diffuse" in message


@pytest.mark.parametrize(
    "content, expected",
    [
        ('<materialx version="1.39"><standard_surface', "is not readable"),
        (
            '<?xml version="1.0"?><materialx version="1.39">'
            '<surfacematerial name="Other" type="material"/></materialx>',
            "has no material 'Gold' (it has: Other)",
        ),
    ],
)
def test_unreadable_mtlx_document_falls_back_to_grey(tmp_path, content, expected):
    (tmp_path / "broken.mtlx").write_text(content)
    scene = load_scene(_stage(tmp_path, "broken.mtlx"))
    assert _by_path(scene, "Paint").diffuse_color.value.tolist() == pytest.approx([0.18] * 3)
    assert any(expected in message and "using grey 0.18 diffuse" in message for message in scene.warnings)


def test_missing_geometry_reference_stays_an_error(tmp_path):
    shutil.copy(DATA / "standard_surface_gold.mtlx", tmp_path)
    shot = _stage(tmp_path, "standard_surface_gold.mtlx", extra=PROP)
    with pytest.raises(RelightError, match=r"stage .*shot.usda: Could not open asset @.*prop.usda@") as error:
        load_scene(shot)
    assert "\n" not in str(error.value)


def test_cli_bakes_a_stage_whose_material_variant_references_mtlx(tmp_path, capsys):
    shutil.copy(DATA / "standard_surface_gold.mtlx", tmp_path)
    shot = _stage(tmp_path, "standard_surface_gold.mtlx")
    status = main(
        [
            "bake",
            str(shot),
            "--camera",
            "/World/Camera",
            "--out",
            str(tmp_path / "out"),
            "--width",
            "8",
            "--height",
            "6",
            "--method",
            "direct",
        ]
    )
    assert status == 0, capsys.readouterr().err
    assert (tmp_path / "out" / "shot.relight.usda").is_file()


def test_material_prim_with_a_missing_usd_reference_is_a_warning(tmp_path):
    shot = _stage(tmp_path, "standard_surface_gold.mtlx")
    reference = "\n            references = @./looks.usda@"
    shot.write_text(shot.read_text().replace('def Material "Paint" (', 'def Material "Paint" (' + reference))
    shutil.copy(DATA / "standard_surface_gold.mtlx", tmp_path)
    scene = load_scene(shot)
    assert any("material /World/Looks/Paint" in message and "looks.usda" in message for message in scene.warnings)


# The mappings ---------------------------------------------------------------------------------


def test_every_example_material_maps_without_falling_back_to_grey(scene):
    assert {material.path for material in scene.materials} == {f"/World/Looks/{name}" for name in LOOKS}
    assert not [message for message in scene.warnings if "grey" in message or "unsupported" in message]
    for material in scene.materials:
        textured = material.diffuse_color.texture is not None
        assert textured or not np.allclose(material.diffuse_color.value, 0.18), material.path


def test_standard_surface_follows_materialx_translation_graph(scene):
    gold = _by_path(scene, "Gold")  # base 1, metalness 1, specular_roughness 0.02
    np.testing.assert_allclose(gold.diffuse_color.value, [0.944, 0.776, 0.373], rtol=1e-6)
    assert (gold.metallic.value[0], gold.roughness.value[0], gold.clearcoat.value[0]) == pytest.approx((1, 0.02, 0))
    # Copper: white metal under a coloured coat: the coat tints the base and its mean is the clearcoat.
    copper = _by_path(scene, "Copper")
    coat_color = np.array([0.96467984, 0.37626296, 0.25818297])
    np.testing.assert_allclose(copper.diffuse_color.value, coat_color, rtol=1e-6)
    assert copper.clearcoat.value[0] == pytest.approx(coat_color.mean(), rel=1e-6)
    assert copper.clearcoat_roughness.value[0] == pytest.approx(0.2)
    carpaint = _by_path(scene, "CarPaint")  # base 0.5 scales base_color
    np.testing.assert_allclose(
        carpaint.diffuse_color.value, 0.5 * np.array([0.1037792, 0.59212029, 0.85064936]), rtol=1e-6
    )
    assert any("SR_carpaint" in message and "specular_anisotropy" in message for message in scene.warnings)


def test_open_pbr_and_usd_preview_surface_mappings(scene):
    carpaint = _by_path(scene, "OpenPbrCarPaint")
    np.testing.assert_allclose(carpaint.diffuse_color.value, [0.1, 0.6, 0.9], rtol=1e-6)
    assert (carpaint.ior.value[0], carpaint.roughness.value[0]) == pytest.approx((1.6, 0.3))
    assert (carpaint.clearcoat.value[0], carpaint.clearcoat_roughness.value[0]) == pytest.approx((1.0, 0.02))
    pearl = [message for message in scene.warnings if "/World/Looks/Pearl" in message]
    assert len(pearl) == 1 and "thin_film_weight" in pearl[0] and "coat_ior" in pearl[0]
    plastic = _by_path(scene, "Plastic")
    np.testing.assert_allclose(plastic.diffuse_color.value, [0.10470402, 0.24188282, 0.81800002], rtol=1e-6)
    assert plastic.roughness.value[0] == pytest.approx(0.32467532)
    assert plastic.documents == (str(DATA / "usd_preview_surface_plastic.mtlx"),)


def test_image_nodes_become_textures_with_their_coordinates(scene):
    uvs = np.array([[0.1, 0.2], [0.37, 0.81], [0.93, 0.55]], np.float32)
    wood = _by_path(scene, "Wood")  # tiledimage x4, sRGB colour, raw roughness
    assert wood.diffuse_color.texture.file.endswith("wood_color.png")
    usd = _by_path(scene, "UsdStandardSurface")  # the same images through USD-authored ND_tiledimage x2
    # Tiling 4 at uv equals tiling 2 at 2 uv: both readers place the same image the same way (the USD
    # one's diffuse is a white metal under a coat coloured by the image: the image again).
    for key in ("diffuse_color", "roughness"):
        from_mtlx = evaluate_materials([wood], np.zeros(3, int), uvs)[key]
        from_usd = evaluate_materials([usd], np.zeros(3, int), 2 * uvs)[key]
        np.testing.assert_allclose(from_mtlx, from_usd, rtol=1e-6, atol=1e-7)
    assert wood.diffuse_color.texture.pixels.max() <= 1.0
    # ND_image_color3 * 0.8 with a mirrored u address mode.
    open_pbr = _by_path(scene, "UsdOpenPbr")
    texture = open_pbr.diffuse_color.texture
    assert (texture.wrap_s, texture.wrap_t) == ("mirror", "repeat")
    raw = select_output(sample_texture(Texture(texture.file, texture.pixels, "mirror", "repeat"), uvs), "rgb")
    np.testing.assert_allclose(
        evaluate_materials([open_pbr], np.zeros(3, int), uvs)["diffuse_color"], 0.8 * raw, rtol=1e-6
    )


USD_UV_TEXTURE = """
    def Material "Tex"
    {
        token outputs:mtlx:surface.connect = </World/Tex/Surface.outputs:out>
        def Shader "Surface"
        {
            uniform token info:id = "ND_standard_surface_surfaceshader"
            color3f inputs:base_color.connect = </World/Tex/Image.outputs:rgb>
            float inputs:specular_roughness.connect = </World/Tex/Image.outputs:g>
            token outputs:out
        }
        def Shader "Image"
        {
            uniform token info:id = "UsdUVTexture"
            asset inputs:file = @./albedo.exr@
            float2 inputs:st.connect = </World/Tex/Coords.outputs:result>
            float4 inputs:scale = (0.5, 0.5, 0.5, 1)
            token inputs:wrapS = "clamp"
            float3 outputs:rgb
            float outputs:g
        }
        def Shader "Coords"
        {
            uniform token info:id = "UsdPrimvarReader_float2"
            string inputs:varname = "st"
            float2 outputs:result
        }
    }"""


def test_materialx_surface_fed_by_usd_uv_texture(tmp_path):
    pixels = np.array([[[0.2, 0.4, 0.6], [0.8, 0.6, 0.4]]], np.float32)
    write_rgb_exr(tmp_path / "albedo.exr", pixels)
    shot = _stage(tmp_path, "unused.mtlx", extra=USD_UV_TEXTURE)
    shot.write_text(shot.read_text().replace("</World/Looks/Paint>", "</World/Tex>"))
    scene = load_scene(shot)
    (material,) = scene.materials
    texture = material.diffuse_color.texture
    assert (texture.wrap_s, texture.wrap_t, texture.st_primvar) == ("clamp", "black", "st")
    values = evaluate_materials([material], np.zeros(2, int), np.array([[0.25, 0.5], [0.75, 0.5]], np.float32))
    np.testing.assert_allclose(values["diffuse_color"], 0.5 * pixels[0], rtol=1e-6)
    np.testing.assert_allclose(values["roughness"], 0.5 * pixels[0, :, 1], rtol=1e-6)


def test_normalmap_node_gives_the_tangent_space_normal(tmp_path):
    pixels = np.array([[[0.5, 0.5, 1.0], [1.0, 0.5, 0.5]]], np.float32)
    write_rgb_exr(tmp_path / "normal.exr", pixels)
    (tmp_path / "bumpy.mtlx").write_text("""<?xml version="1.0"?>
<materialx version="1.39" colorspace="lin_rec709">
  <image name="normal_image" type="vector3"><input name="file" type="filename" value="normal.exr"/></image>
  <normalmap name="bump" type="vector3">
    <input name="in" type="vector3" nodename="normal_image"/><input name="scale" type="float" value="0.5"/>
  </normalmap>
  <standard_surface name="SR" type="surfaceshader">
    <input name="normal" type="vector3" nodename="bump"/>
  </standard_surface>
  <surfacematerial name="Gold" type="material"><input name="surfaceshader" type="surfaceshader" nodename="SR"/>
  </surfacematerial>
</materialx>""")
    scene = load_scene(_stage(tmp_path, "bumpy.mtlx"))
    paint = _by_path(scene, "Paint")
    normals = evaluate_materials([paint], np.zeros(2, int), np.array([[0.25, 0.5], [0.75, 0.5]], np.float32))
    # (2 v - 1) with x and y times the normalmap's scale 0.5.
    np.testing.assert_allclose(normals["normal_tangent"], [[0, 0, 1], [0.5, 0, 0]], atol=1e-6)


def test_affine_arithmetic_on_textures_is_exact():
    rng = np.random.default_rng(3)
    texture = Texture(
        "image.exr",
        rng.random((5, 4, 3), dtype=np.float32),
        output="g",
        scale=np.array([1, 0.5, 1, 1], np.float32),
        bias=np.array([0, 0.1, 0, 0], np.float32),
    )
    uvs = rng.random((50, 2))
    grey = MaterialInput(np.array([0.3], np.float32), texture)
    samples = select_output(sample_texture(texture, uvs), "g")
    tinted = scaled(MaterialInput(np.full(3, 0.3, np.float32), texture), [0.2, 0.4, 0.8], [0.0, 0.1, 0.2])
    np.testing.assert_allclose(
        select_output(sample_texture(tinted.texture, uvs), tinted.texture.output),
        samples * [0.2, 0.4, 0.8] + [0.0, 0.1, 0.2],
        rtol=1e-5,
        atol=1e-6,
    )
    scaled_grey = scaled(grey, 2.0, -0.5)
    np.testing.assert_allclose(
        select_output(sample_texture(scaled_grey.texture, uvs), "g"), 2 * samples - 0.5, rtol=1e-5, atol=1e-6
    )
    colour = Texture("image.exr", texture.pixels)
    mean = channel_mean(MaterialInput(np.zeros(3, np.float32), colour))
    np.testing.assert_allclose(
        select_output(sample_texture(mean.texture, uvs), mean.texture.output)[:, 0],
        sample_texture(colour, uvs)[:, :3].mean(axis=1),
        rtol=1e-5,
        atol=1e-6,
    )


def test_bake_inputs_include_the_mtlx_documents(scene):
    files = input_files(scene)
    assert str((DATA / "open_pbr_pearl.mtlx").resolve()) in files
    assert str((DATA / "images" / "wood_roughness.png").resolve()) in files


# Relighting -----------------------------------------------------------------------------------

# 64x48, direct only. Supersampling 4: the gold ball (roughness 0.02) reflects the sphere light in
# a highlight smaller than a pixel, which 2x2 sub-samples alias (38.9 dB there, 41.1 dB at 4x4).
WIDTH, HEIGHT, SPP, THRESHOLD = 64, 48, 1024, 38.0


@pytest.mark.slow
def test_relit_materialx_examples_match_the_reference(tmp_path):
    scene = load_scene(SHOT, width=WIDTH, height=HEIGHT)
    camera = find_camera(scene, "/World/Camera")
    cache = bake_direct(scene, camera, tmp_path / "cache", "shot", supersampling=4)
    image = Relighter.from_cache(cache, device="cpu").render().numpy()
    reference = PathTracer(scene, ReferenceSettings(spp=SPP, max_bounces=0, seed=7)).render(camera)
    unclamped = reference.mean <= 1.0
    noise_psnr = 10 * np.log10(unclamped.mean() / float(np.mean(reference.variance * unclamped)))
    assert noise_psnr > THRESHOLD + 6, f"reference too noisy to judge ({noise_psnr:.1f} dB)"
    value = psnr(image, reference.mean)
    if value < THRESHOLD:
        write_rgb_exr(tmp_path / "relit.exr", image)
        write_rgb_exr(tmp_path / "reference.exr", reference.mean)
    assert value >= THRESHOLD, f"{value:.2f} dB (images in {tmp_path})"
    assert float(image.mean() / reference.mean.mean()) == pytest.approx(1.0, abs=0.03)
