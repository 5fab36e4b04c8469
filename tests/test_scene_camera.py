"""Cameras: reading, conforming, primary rays and projection, checked against pinhole geometry."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom, UsdRender

from pipeline.errors import RelightError
from pipeline.scene.camera import camera_rays, crop, image_resolution, project, read_cameras

DEFAULT = Usd.TimeCode.Default()


def _stage_with_camera(
    focal=35.0,
    horizontal=36.0,
    vertical=24.0,
    rotate=(20.0, -30.0, 10.0),
    translate=(1.0, 2.0, 3.0),
    offsets=(0.0, 0.0),
) -> Usd.Stage:
    stage = Usd.Stage.CreateInMemory()
    camera = UsdGeom.Camera.Define(stage, "/Cam")
    camera.AddTranslateOp().Set(Gf.Vec3d(*translate))
    camera.AddRotateXYZOp().Set(Gf.Vec3f(*rotate))
    camera.CreateFocalLengthAttr(focal)
    camera.CreateHorizontalApertureAttr(horizontal)
    camera.CreateVerticalApertureAttr(vertical)
    camera.CreateHorizontalApertureOffsetAttr(offsets[0])
    camera.CreateVerticalApertureOffsetAttr(offsets[1])
    return stage


def _camera(stage, width=None, height=None, warnings=None):
    return read_cameras(stage, DEFAULT, width, height, warnings)["/Cam"]


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.arccos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


def test_world_from_camera_is_the_transposed_usd_transform():
    stage = _stage_with_camera()
    camera = _camera(stage, 36, 24)
    usd = np.array(UsdGeom.Camera(stage.GetPrimAtPath("/Cam")).ComputeLocalToWorldTransform(DEFAULT))
    np.testing.assert_allclose(camera.world_from_camera, usd.T, atol=1e-12)
    np.testing.assert_allclose(camera.world_from_camera[:3, 3], [1, 2, 3])


def test_centre_ray_is_the_camera_minus_z_axis():
    stage = _stage_with_camera()
    camera = _camera(stage, 31, 21)  # odd sizes: a pixel centre sits on the axis
    origins, directions = camera_rays(camera)
    assert origins.shape == directions.shape == (21, 31, 3)
    assert origins.dtype == directions.dtype == np.float32
    minus_z = -camera.world_from_camera[:3, 2] / np.linalg.norm(camera.world_from_camera[:3, 2])
    np.testing.assert_allclose(directions[10, 15], minus_z, atol=1e-6)
    np.testing.assert_allclose(origins[0, 0], [1, 2, 3], atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=-1), 1.0, atol=1e-6)


def test_corner_and_edge_rays_match_the_field_of_view():
    stage = _stage_with_camera(focal=35.0, horizontal=36.0, vertical=24.0)
    camera = _camera(stage, 36, 24)
    axis = -camera.world_from_camera[:3, 2]
    # The exact top-left corner of the image: pixel (0, 0) with offset (0, 0).
    offsets = np.full((24, 36, 2), 0.5)
    offsets[0, 0] = 0.0
    _, directions = camera_rays(camera, offsets)
    expected = np.arctan(np.hypot(18.0, 12.0) / 35.0)
    assert _angle(directions[0, 0], axis) == pytest.approx(expected, abs=1e-6)
    # The top-left corner is up and to the left in the camera frame.
    local = camera.world_from_camera[:3, :3].T @ directions[0, 0]
    assert local[0] < 0 and local[1] > 0 and local[2] < 0
    # Left edge to right edge through the middle row spans Gf's horizontal field of view.
    offsets = np.full((24, 36, 2), 0.5)
    offsets[12, 0] = (0.0, 0.0)
    offsets[12, 35] = (1.0, 0.0)
    _, directions = camera_rays(camera, offsets)
    fov = UsdGeom.Camera(stage.GetPrimAtPath("/Cam")).GetCamera(DEFAULT).GetFieldOfView(Gf.Camera.FOVHorizontal)
    assert np.degrees(_angle(directions[12, 0], directions[12, 35])) == pytest.approx(fov, rel=1e-5)


def test_aperture_offset_shifts_the_principal_point():
    stage = _stage_with_camera(
        focal=50.0, horizontal=20.0, vertical=20.0, rotate=(0, 0, 0), translate=(0, 0, 0), offsets=(5.0, -2.0)
    )
    camera = _camera(stage, 2, 2)
    offsets = np.full((2, 2, 2), 0.5)
    offsets[1, 1] = 0.0  # the image centre
    _, directions = camera_rays(camera, offsets)
    expected = np.array([5.0, -2.0, -50.0]) / np.linalg.norm([5.0, -2.0, -50.0])
    np.testing.assert_allclose(directions[1, 1], expected, atol=1e-6)


def test_a_crop_sees_what_its_pixels_of_the_whole_image_see():
    camera = _camera(_stage_with_camera(offsets=(1.5, -0.5)), 48, 30)
    rng = np.random.default_rng(0)
    offsets = rng.random((30, 48, 2))
    _, whole = camera_rays(camera, offsets)
    window = crop(camera, 7, 11, 20, 13)
    assert (window.width, window.height) == (20, 13)
    origins, directions = camera_rays(window, offsets[11:24, 7:27])
    np.testing.assert_allclose(directions, whole[11:24, 7:27], atol=1e-6)
    np.testing.assert_array_equal(origins[0, 0], camera.world_from_camera[:3, 3].astype(np.float32))
    assert crop(camera, 0, 0, 48, 30) == camera


@pytest.mark.parametrize("window", [(40, 0, 9, 5), (0, 26, 5, 5), (3, 3, 0, 4)])
def test_a_crop_outside_the_image_is_refused(window):
    with pytest.raises(ValueError, match="leaves the 48x30 image of /Cam"):
        crop(_camera(_stage_with_camera(), 48, 30), *window)


def test_aspect_mismatch_keeps_the_horizontal_aperture():
    stage = _stage_with_camera(horizontal=36.0, vertical=24.0)
    camera = _camera(stage, 100, 100)
    assert camera.horizontal_aperture == pytest.approx(36.0)
    assert camera.vertical_aperture == pytest.approx(36.0)
    camera = _camera(stage, 200, 50)
    assert camera.vertical_aperture == pytest.approx(9.0)


def test_project_inverts_camera_rays():
    camera = _camera(_stage_with_camera(offsets=(1.5, -0.7)), 40, 30)
    rng = np.random.default_rng(7)
    offsets = rng.random((30, 40, 2))
    origins, directions = camera_rays(camera, offsets)
    distance = rng.uniform(1.0, 20.0, (30, 40, 1))
    points = (origins + distance * directions).reshape(-1, 3)
    pixels, depth = project(camera, points)
    rows, cols = np.mgrid[0:30, 0:40]
    expected = np.stack((cols + offsets[..., 0], rows + offsets[..., 1]), -1).reshape(-1, 2)
    np.testing.assert_allclose(pixels, expected, atol=2e-3)
    # Depth along the view axis = distance * cos(angle to the axis).
    axis = -camera.world_from_camera[:3, 2]
    np.testing.assert_allclose(depth, (distance * (directions @ axis)[..., None]).ravel(), rtol=1e-5)
    behind_pixels, behind_depth = project(camera, origins[:1, 0] - directions[0, :1])
    assert behind_depth[0] < 0 and np.isnan(behind_pixels).all()


def _settings(stage: Usd.Stage, path: str, resolution) -> UsdRender.Settings:
    settings = UsdRender.Settings.Define(stage, path)
    settings.CreateResolutionAttr(Gf.Vec2i(*resolution))
    return settings


def test_resolution_from_render_settings_and_overrides():
    stage = _stage_with_camera()
    assert image_resolution(stage) == (640, 480)
    _settings(stage, "/Render/First", (320, 200))
    _settings(stage, "/Render/Second", (1920, 1080))
    assert image_resolution(stage) == (320, 200)  # the first found
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Second")
    assert image_resolution(stage) == (1920, 1080)  # the one the stage names
    camera = _camera(stage, width=100)
    assert (camera.width, camera.height) == (100, 1080)


@pytest.mark.parametrize("width, height", [(0, 10), (10, -1), (2.5, 10)])
def test_bad_image_size_is_a_relight_error(width, height):
    with pytest.raises(RelightError, match=r"width|height"):
        image_resolution(_stage_with_camera(), width, height)


def test_orthographic_camera_is_skipped_with_a_warning():
    stage = _stage_with_camera()
    UsdGeom.Camera.Define(stage, "/Ortho").CreateProjectionAttr("orthographic")
    warnings: list[str] = []
    cameras = read_cameras(stage, DEFAULT, warnings=warnings)
    assert list(cameras) == ["/Cam"]
    assert any("/Ortho" in w and "orthographic" in w for w in warnings)


def test_exposure_scale_from_the_camera_exposure_attributes():
    stage = _stage_with_camera()
    camera = UsdGeom.Camera(stage.GetPrimAtPath("/Cam"))
    camera.CreateExposureAttr(1.0)
    camera.CreateExposureFStopAttr(2.0)
    # responsivity * time * (iso / 100) * 2^exposure / fStop^2 = 1 * 1 * 1 * 2 / 4
    assert _camera(stage).exposure_scale == pytest.approx(0.5)
