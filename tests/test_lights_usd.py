"""UsdLux prims <-> Light: every type round-trips, layers compose, bad values raise one clear line."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import OpenImageIO as oiio
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux

from pipeline.errors import RelightError
from pipeline.scene.lights import read_lights
from relight_torch.lights.image import read_linear_rgb
from relight_torch.lights.light import Light, LightKind, Shaping
from relight_torch.lights.usd import iter_light_prims, read_light, read_lights_layer, write_light, write_lights_layer
from relight_torch.schema import register_schemas

DEFAULT = Usd.TimeCode.Default()


def write_image(path, pixels: np.ndarray) -> None:
    output = oiio.ImageOutput.create(str(path))
    format_ = oiio.UINT8 if pixels.dtype == np.uint8 else oiio.FLOAT
    output.open(str(path), oiio.ImageSpec(pixels.shape[1], pixels.shape[0], pixels.shape[2], format_))
    output.write_image(pixels)
    output.close()


def assert_same(a, b, where: str = "light") -> None:
    """Field-by-field equality of (nested) light dataclasses, arrays exactly."""
    assert type(a) is type(b), where
    for field in dataclasses.fields(a):
        x, y = getattr(a, field.name), getattr(b, field.name)
        if dataclasses.is_dataclass(x):
            assert_same(x, y, f"{where}.{field.name}")
        elif isinstance(x, np.ndarray):
            np.testing.assert_array_equal(x, y, err_msg=f"{where}.{field.name}")
        else:
            assert x == y, f"{where}.{field.name}: {x!r} != {y!r}"


@pytest.fixture
def shot(tmp_path):
    """A Z-up shot with every light type, non-default inputs, transforms under a moved parent, images."""
    register_schemas()
    write_image(tmp_path / "sky.exr", np.random.default_rng(0).uniform(0, 4, (8, 16, 3)).astype(np.float32))
    write_image(tmp_path / "panel.exr", np.arange(2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3))
    write_image(tmp_path / "gobo.png", np.full((4, 4, 3), 128, np.uint8))
    stage = Usd.Stage.CreateNew(str(tmp_path / "shot.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    world = UsdGeom.Xform.Define(stage, "/World")
    world.AddTranslateOp().Set(Gf.Vec3d(1, 2, 3))
    world.AddRotateXOp().Set(30.0)

    key = UsdLux.SphereLight.Define(stage, "/World/Key")
    key.CreateRadiusAttr(0.3)
    key.CreateTreatAsPointAttr(True)
    key.CreateIntensityAttr(5.0)
    key.CreateExposureAttr(1.5)
    key.CreateColorAttr(Gf.Vec3f(1.0, 0.5, 0.25))
    key.CreateEnableColorTemperatureAttr(True)
    key.CreateColorTemperatureAttr(4000.0)
    key.CreateNormalizeAttr(True)
    key.CreateDiffuseAttr(0.5)
    key.CreateSpecularAttr(2.0)
    UsdGeom.Xformable(key).AddTranslateOp().Set(Gf.Vec3d(0, 0, 4))
    UsdGeom.Xformable(key).AddScaleOp().Set(Gf.Vec3f(2, 2, 2))
    shaping = UsdLux.ShapingAPI.Apply(key.GetPrim())
    shaping.CreateShapingConeAngleAttr(40.0)
    shaping.CreateShapingConeSoftnessAttr(0.2)
    shaping.CreateShapingFocusAttr(1.5)
    shaping.CreateShapingFocusTintAttr(Gf.Vec3f(0.1, 0.2, 0.3))
    shadow = UsdLux.ShadowAPI.Apply(key.GetPrim())
    shadow.CreateShadowColorAttr(Gf.Vec3f(0.2, 0.1, 0.0))
    shadow.CreateShadowDistanceAttr(12.0)
    shadow.CreateShadowFalloffAttr(3.0)
    key.GetPrim().ApplyAPI("RelightBarzelLightAPI")
    for name, value in {
        "relight:barzel:window:enable": True,
        "relight:barzel:window:width": 1.2,
        "relight:barzel:window:roundness": 0.5,
        "relight:barzel:barnDoor:top": 35.0,
        "relight:barzel:cookie:file": Sdf.AssetPath("gobo.png"),
        "relight:barzel:cookie:scale": Gf.Vec2f(2, 3),
        "relight:barzel:near:end": 1.0,
        "relight:barzel:far:start": 8.0,
        "relight:barzel:far:end": 9.0,
        "relight:lightGroup": "keys",
    }.items():
        key.GetPrim().GetAttribute(name).Set(value)

    panel = UsdLux.RectLight.Define(stage, "/World/Panel")
    panel.CreateWidthAttr(2.0)
    panel.CreateHeightAttr(0.5)
    panel.CreateTextureFileAttr(Sdf.AssetPath("panel.exr"))
    UsdGeom.Xformable(panel).AddScaleOp().Set(Gf.Vec3f(1, 3, 2))
    disk = UsdLux.DiskLight.Define(stage, "/World/Disk")
    disk.CreateRadiusAttr(0.7)
    UsdGeom.Xformable(disk).AddRotateYOp().Set(45.0)
    tube = UsdLux.CylinderLight.Define(stage, "/World/Tube")
    tube.CreateLengthAttr(3.0)
    tube.CreateRadiusAttr(0.1)
    tube.CreateTreatAsLineAttr(True)
    sun = UsdLux.DistantLight.Define(stage, "/World/Sun")
    sun.CreateAngleAttr(2.0)
    dome = UsdLux.DomeLight.Define(stage, "/Sky")
    dome.CreateTextureFileAttr(Sdf.AssetPath("sky.exr"))
    dome.CreateTextureFormatAttr(UsdLux.Tokens.latlong)
    UsdGeom.Xformable(dome).AddRotateZOp().Set(90.0)
    UsdLux.DomeLight_1.Define(stage, "/SkyZ")  # poleAxis 'scene' on a Z-up stage
    stage.Save()
    return stage


def test_reads_every_input(shot, tmp_path):
    lights = {light.path: light for light in map(read_light, iter_light_prims(shot, DEFAULT))}
    assert set(lights) == {"/World/Key", "/World/Panel", "/World/Disk", "/World/Tube", "/World/Sun", "/Sky", "/SkyZ"}
    key = lights["/World/Key"]
    assert (key.kind, key.treat_as_point, key.intensity, key.exposure) == (LightKind.SPHERE, True, 5, 1.5)
    assert key.radius == pytest.approx(0.3)
    assert key.color == (1.0, 0.5, 0.25) and key.normalize and key.enable_color_temperature
    assert (key.diffuse, key.specular, key.color_temperature) == (0.5, 2.0, 4000.0)
    assert key.shaping == Shaping(
        focus=1.5, focus_tint=pytest.approx((0.1, 0.2, 0.3)), cone_angle=40.0, cone_softness=pytest.approx(0.2)
    )
    assert (key.shadow.color, key.shadow.distance, key.shadow.falloff) == (pytest.approx((0.2, 0.1, 0.0)), 12.0, 3.0)
    assert key.barzel.barn_door_top == 35.0 and key.barzel.barn_door_left == 180.0 and key.barzel.window_enable
    assert key.barzel.cookie_file == str(tmp_path / "gobo.png") and key.barzel.cookie_scale == (2.0, 3.0)
    np.testing.assert_allclose(key.barzel.cookie, ((128 / 255 + 0.055) / 1.055) ** 2.4, rtol=1e-6)  # sRGB decoded
    assert key.light_group == "keys" and lights["/World/Disk"].light_group == "Disk"
    # world_from_light = parent (translate, rotateX 30) then the light's own translate and scale.
    angle = math.radians(30.0)
    expected_origin = np.array([1, 2, 3]) + 4.0 * np.array([0, -math.sin(angle), math.cos(angle)])
    np.testing.assert_allclose(key.world_from_light[:3, 3], expected_origin, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(key.world_from_light[:3, :3], axis=0), 2.0)
    assert lights["/World/Panel"].texture.shape == (2, 3, 3) and lights["/World/Panel"].texture[1, 2, 2] == 17.0
    assert lights["/World/Disk"].shaping is None and lights["/World/Disk"].barzel is None
    assert lights["/Sky"].pole_axis == "Y" and lights["/SkyZ"].pole_axis == "Z"
    assert lights["/World/Sun"].intensity == 50000.0 and lights["/World/Sun"].angle == 2.0


def test_write_then_read_gives_equal_lights(shot):
    lights = [read_light(prim) for prim in iter_light_prims(shot, DEFAULT)]
    register_schemas()
    copy = Usd.Stage.CreateInMemory()
    for light in lights:
        write_light(copy, light)
    again = {light.path: light for light in map(read_light, iter_light_prims(copy, DEFAULT))}
    for light in lights:
        assert_same(light, again[light.path], light.path)


def test_lights_layer_round_trip_and_composition_over_the_shot(shot, tmp_path):
    lights = [read_light(prim) for prim in iter_light_prims(shot, DEFAULT)]
    edited = [dataclasses.replace(light, intensity=light.intensity * 2, shaping=None) for light in lights]
    write_lights_layer(tmp_path / "edits.usda", edited)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["edits.usda", "gobo.png", "panel.exr", "shot.usda", "sky.exr"]
    for light, back in zip(edited, read_lights_layer(tmp_path / "edits.usda"), strict=True):
        assert_same(light, back, light.path)
    # Composed as the strongest sublayer, the edits win and transforms stay put despite /World's xform.
    root = Sdf.Layer.CreateAnonymous(".usda")
    root.subLayerPaths = [str(tmp_path / "edits.usda"), str(tmp_path / "shot.usda")]
    composed = Usd.Stage.Open(root)
    for light in edited:
        assert_same(light, read_light(composed.GetPrimAtPath(light.path)), light.path)


def test_read_lights_walks_instances_skips_hidden_and_warns(tmp_path):
    register_schemas()
    stage = Usd.Stage.CreateInMemory()
    key = UsdLux.SphereLight.Define(stage, "/World/Key")
    move = UsdGeom.Xformable(key).AddTranslateOp()
    move.Set(Gf.Vec3d(0, 0, 0), 1.0)
    move.Set(Gf.Vec3d(0, 0, 4), 2.0)
    UsdGeom.Xform.Define(stage, "/World/Hidden").MakeInvisible()
    UsdLux.DiskLight.Define(stage, "/World/Hidden/Fill")
    stage.CreateClassPrim("/Protos")
    UsdLux.SphereLight.Define(stage, "/Protos/Lamp/Bulb")
    for name, x in (("LampA", 1.0), ("LampB", -1.0)):
        lamp = UsdGeom.Xform.Define(stage, f"/World/{name}")
        lamp.AddTranslateOp().Set(Gf.Vec3d(x, 0, 0))
        lamp.GetPrim().GetReferences().AddInternalReference("/Protos/Lamp")
        lamp.GetPrim().SetInstanceable(True)
    glow = UsdGeom.Mesh.Define(stage, "/World/Glow")
    UsdLux.MeshLightAPI.Apply(glow.GetPrim())
    instancer = UsdGeom.PointInstancer.Define(stage, "/World/Scatter")
    UsdLux.SphereLight.Define(stage, "/World/Scatter/Proto")
    warnings: list[str] = []
    lights = read_lights(stage, Usd.TimeCode(2.0), warnings)
    assert [light.path for light in lights] == ["/World/Key", "/World/LampA/Bulb", "/World/LampB/Bulb"]
    np.testing.assert_allclose(lights[0].world_from_light[:3, 3], [0, 0, 4])
    np.testing.assert_allclose(lights[2].world_from_light[:3, 3], [-1, 0, 0])
    assert len(warnings) == 1 and "/World/Glow" in warnings[0] and "not supported" in warnings[0]
    assert instancer  # the PointInstancer's prototype light was pruned, not read


def light_stage(kind=UsdLux.SphereLight):
    register_schemas()
    stage = Usd.Stage.CreateInMemory()
    return stage, kind.Define(stage, "/L").GetPrim()


@pytest.mark.parametrize(
    "edit, message",
    [
        (
            lambda p: p.GetAttribute("inputs:intensity").Set(-1.0),
            r"^/L: inputs:intensity = -1\.0 must be finite and >= 0$",
        ),
        (lambda p: p.GetAttribute("inputs:radius").Set(float("nan")), r"^/L: inputs:radius = nan must be finite"),
        (lambda p: p.GetAttribute("inputs:exposure").Set(float("inf")), r"^/L: inputs:exposure = inf must be finite$"),
        (lambda p: p.GetAttribute("inputs:color").Set(Gf.Vec3f(-1, 0, 0)), r"^/L: inputs:color = .* >= 0$"),
        (lambda p: p.GetAttribute("inputs:colorTemperature").Set(0.0), r"^/L: inputs:colorTemperature = 0\.0 .* > 0$"),
        (lambda p: UsdLux.ShapingAPI.Apply(p).CreateShapingConeAngleAttr(-5.0), r"^/L: inputs:shaping:cone:angle = -5"),
        (
            lambda p: (p.ApplyAPI("RelightBarzelLightAPI"), p.GetAttribute("relight:barzel:window:width").Set(0.0)),
            r"^/L: relight:barzel:window:width = 0\.0 must be finite and > 0$",
        ),
        (
            lambda p: (
                p.ApplyAPI("RelightBarzelLightAPI"),
                p.GetAttribute("relight:barzel:near:start").Set(2.0),
                p.GetAttribute("relight:barzel:near:end").Set(1.0),
            ),
            r"^/L: relight:barzel:near:start must lie in",
        ),
        (
            lambda p: UsdGeom.Xformable(p).AddScaleOp().Set(Gf.Vec3f(1, 2, 1)),
            r"^/L: SphereLight needs a rotation and one",
        ),
    ],
)
def test_bad_values_raise_one_line_naming_prim_and_attribute(edit, message):
    stage, prim = light_stage()
    edit(prim)
    with pytest.raises(ValueError, match=message):
        read_light(prim)
    with pytest.raises(RelightError, match=message):
        read_lights(stage, DEFAULT, [])


def test_unsupported_type_raises_but_the_walker_warns():
    stage, prim = light_stage(UsdLux.PortalLight)
    with pytest.raises(ValueError, match=r"^/L: unsupported light type 'PortalLight'"):
        read_light(prim)
    warnings: list[str] = []
    assert read_lights(stage, DEFAULT, warnings) == []
    assert warnings == ["/L: light type 'PortalLight' is not supported; skipped"]


def test_filters_and_portals_are_ignored_with_warnings():
    stage, prim = light_stage(UsdLux.DomeLight)
    UsdLux.LightAPI(prim).GetFiltersRel().AddTarget("/Blocker")
    UsdLux.DomeLight(prim).CreatePortalsRel().AddTarget("/Window")
    warnings: list[str] = []
    assert [light.path for light in read_lights(stage, DEFAULT, warnings)] == ["/L"]
    assert warnings == [
        "/L: light:filters are not supported; ignored",
        "/L: dome light portals are not supported; ignored",
    ]


def test_missing_image_raises():
    _stage, prim = light_stage(UsdLux.RectLight)
    UsdLux.RectLight(prim).CreateTextureFileAttr(Sdf.AssetPath("missing.exr"))
    with pytest.raises(ValueError, match=r"^/L: inputs:texture:file: image 'missing.exr' not found$"):
        read_light(prim)


def test_unsupported_dome_format_raises(tmp_path):
    write_image(tmp_path / "probe.exr", np.ones((4, 4, 3), np.float32))
    _stage, prim = light_stage(UsdLux.DomeLight)
    UsdLux.DomeLight(prim).CreateTextureFileAttr(Sdf.AssetPath(str(tmp_path / "probe.exr")))
    UsdLux.DomeLight(prim).CreateTextureFormatAttr(UsdLux.Tokens.angular)
    with pytest.raises(ValueError, match=r"^/L: inputs:texture:format 'angular' is not supported"):
        read_light(prim)


def test_read_linear_rgb_grey_and_errors(tmp_path):
    write_image(tmp_path / "grey.exr", np.full((2, 2, 1), 0.5, np.float32))
    np.testing.assert_array_equal(read_linear_rgb(tmp_path / "grey.exr"), np.full((2, 2, 3), 0.5, np.float32))
    with pytest.raises(ValueError, match="cannot read image"):
        read_linear_rgb(tmp_path / "absent.exr")


def test_light_dataclass_defaults_match_the_usd_fallbacks():
    _stage, prim = light_stage(UsdLux.RectLight)
    assert_same(read_light(prim), Light("/L", LightKind.RECT, light_group="L"))
