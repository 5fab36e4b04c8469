"""`load_scene` end to end: bad input (each case one `RelightError` line naming the culprit),
light-edit layers, time codes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, UsdLux, UsdUtils

from pipeline.errors import RelightError
from pipeline.scene import find_camera, load_scene
from relight_torch.stage import open_stage


def _write_shot(directory: Path, *, with_mesh: bool = True, with_light: bool = True) -> Path:
    """A small shot: a quad, a camera, a sphere light; Z up, centimetres."""
    path = directory / "shot.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    if with_mesh:
        mesh = UsdGeom.Mesh.Define(stage, "/World/Quad")
        mesh.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)])
        mesh.CreateFaceVertexCountsAttr([4])
        mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
        mesh.CreateSubdivisionSchemeAttr("none")
    UsdGeom.Camera.Define(stage, "/World/CamA")
    UsdGeom.Camera.Define(stage, "/World/CamB")
    if with_light:
        UsdLux.SphereLight.Define(stage, "/World/Key").CreateIntensityAttr(5.0)
    stage.Save()
    return path


def _single_line(error: pytest.ExceptionInfo) -> str:
    message = str(error.value)
    assert "\n" not in message
    return message


def test_missing_file(tmp_path):
    with pytest.raises(RelightError) as error:
        load_scene(tmp_path / "nowhere.usda")
    assert "nowhere.usda" in _single_line(error)


@pytest.mark.parametrize("name, content", [("garbage.usda", "this is not usd\n"), ("image.png", "\x89PNG not a stage")])
def test_not_a_usd_file(tmp_path, name, content):
    path = tmp_path / name
    path.write_text(content)
    with pytest.raises(RelightError) as error:
        open_stage(path)
    message = _single_line(error)
    assert name in message and "not a readable USD file" in message


def test_missing_lights_layer(tmp_path):
    with pytest.raises(RelightError) as error:
        open_stage(_write_shot(tmp_path), tmp_path / "lights.usda")
    assert "lights layer" in _single_line(error) and "lights.usda" in str(error.value)


def test_no_meshes_is_an_error(tmp_path):
    with pytest.raises(RelightError) as error:
        load_scene(_write_shot(tmp_path, with_mesh=False))
    assert "no renderable" in _single_line(error)


def test_no_lights_is_only_a_warning(tmp_path):
    scene = load_scene(_write_shot(tmp_path, with_light=False))
    assert scene.lights == []
    assert any("no lights" in w for w in scene.warnings)


def test_unknown_camera_lists_the_cameras_that_exist(tmp_path):
    scene = load_scene(_write_shot(tmp_path))
    assert find_camera(scene, "/World/CamB").path == "/World/CamB"
    with pytest.raises(RelightError) as error:
        find_camera(scene, "/World/Nope")
    message = _single_line(error)
    assert "/World/Nope" in message and "/World/CamA, /World/CamB" in message


def test_lights_layer_is_the_strongest_sublayer_and_keeps_the_shot_metadata(tmp_path):
    shot = _write_shot(tmp_path)
    lights = Sdf.Layer.CreateNew(str(tmp_path / "lights.usda"))
    edit = Usd.Stage.Open(lights)
    edit.OverridePrim("/World/Key").CreateAttribute("inputs:intensity", Sdf.ValueTypeNames.Float).Set(42.0)
    UsdLux.DistantLight.Define(edit, "/World/Sun")
    lights.Save()
    stage = open_stage(shot, lights.identifier)
    assert UsdGeom.GetStageUpAxis(stage) == "Z"
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(0.01)
    assert UsdLux.SphereLight(stage.GetPrimAtPath("/World/Key")).GetIntensityAttr().Get() == 42.0
    scene = load_scene(shot, lights_layer=tmp_path / "lights.usda")
    assert sorted(light.path for light in scene.lights) == ["/World/Key", "/World/Sun"]
    assert scene.up_axis == "Z" and scene.meters_per_unit == pytest.approx(0.01)
    assert scene.source == str(shot.resolve())


@pytest.mark.parametrize("start_time_code, time, expected_x", [(None, None, 0.0), (2.0, None, 1.0), (None, 1.5, 0.5)])
def test_animated_points_read_at_the_first_frame_or_the_given_time(tmp_path, start_time_code, time, expected_x):
    path = _write_shot(tmp_path)
    stage = Usd.Stage.Open(str(path))
    points = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Quad")).GetPointsAttr()
    square = np.array([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)], np.float32)
    points.Clear()  # only time samples: nothing at the default time
    points.Set(square.tolist(), 1.0)
    points.Set((square + [1, 0, 0]).tolist(), 2.0)
    if start_time_code is not None:
        stage.SetStartTimeCode(start_time_code)
        stage.SetEndTimeCode(start_time_code)
    stage.Save()
    scene = load_scene(path, time=time)
    assert scene.geometry.positions[..., 0].min() == pytest.approx(expected_x)


@pytest.mark.parametrize("suffix", [".usdc", ".usdz"])
def test_crate_and_package_files_open(tmp_path, suffix):
    source = _write_shot(tmp_path)
    path = tmp_path / f"packed{suffix}"
    if suffix == ".usdz":
        assert UsdUtils.CreateNewUsdzPackage(str(source), str(path))
    else:
        Sdf.Layer.FindOrOpen(str(source)).Export(str(path))
    scene = load_scene(path)
    assert scene.geometry.num_triangles == 2
    assert sorted(scene.cameras) == ["/World/CamA", "/World/CamB"]
