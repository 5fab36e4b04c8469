"""Stages written by others (tests/data/scene, see PROVENANCE.md) load with sane counts, and
`relight info` describes them."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest

from pipeline.commands import info
from pipeline.commands.info import describe_stage
from pipeline.errors import RelightError
from pipeline.scene import load_scene
from pipeline.scene.subdivide import triangle_count

DATA = Path(__file__).parent / "data" / "scene"
TEAPOT_SHOT = DATA / "usdwg_teapot" / "shot_utah.usda"
PREVIEW = DATA / "openusd_previewsurface_tests"


def test_utah_teapot_shot():
    scene = load_scene(TEAPOT_SHOT)
    # The teapot's Catmull-Clark cage (1236 quads) refined 3 times for the 640x480 camera (the
    # level at which its control points are within dicing.FLAT_PIXELS of the limit) + the floor quad.
    assert scene.geometry.num_triangles == triangle_count(np.full(1236, 4), "catmullClark", 3) + 2 == 158210
    assert [o.path for o in scene.objects] == ["/Teapot/Geometry", "/Shot/Floor"]
    assert scene.up_axis == "Y" and scene.meters_per_unit == 1.0
    teapot = scene.geometry.positions[scene.geometry.object_ids == 0].reshape(-1, 3)
    # Inside the authored extent of /Teapot/Geometry (the cage's), touching its bottom (a boundary
    # crease) and close to it elsewhere (the limit surface lies inside the cage's hull).
    extent_min, extent_max = np.array([-0.1526284, 0.0, -0.262063]), np.array([0.1526284, 0.22956148, 0.2289426])
    assert (teapot.min(0) >= extent_min - 1e-6).all() and (teapot.max(0) <= extent_max + 1e-6).all()
    np.testing.assert_allclose(teapot.min(0), extent_min, atol=4e-3)
    np.testing.assert_allclose(teapot.max(0), extent_max, atol=4e-3)
    assert np.isfinite(scene.geometry.normals).all()
    assert sorted(light.kind.value for light in scene.lights) == ["RectLight", "SphereLight"]
    camera = scene.cameras["/Shot/Cam"]
    assert (camera.focal_length, camera.horizontal_aperture) == (35.0, 36.0)
    assert (camera.width, camera.height) == (640, 480)


def test_implicit_spheres_with_an_instanced_material():
    scene = load_scene(PREVIEW / "testPreviewSurfaceInstancedMaterial.usda")
    assert [o.path for o in scene.objects] == ["/Scene/Geom/Sphere1", "/Scene/Geom/Sphere2"]
    assert scene.up_axis == "Z"
    paths = {scene.materials[i].path for i in np.unique(scene.geometry.material_ids)}
    assert paths == {"/Scene/Looks/MaterialPrototype", "/Scene/Looks/MaterialInstance"}
    for object_id, centre_x in enumerate([-5.0, 5.0]):
        corners = scene.geometry.positions[scene.geometry.object_ids == object_id].reshape(-1, 3)
        radius = np.linalg.norm(corners - [centre_x, 0, 0], axis=-1)
        np.testing.assert_allclose(radius, 1.0, atol=1e-5)


def test_referenced_planes_and_a_cube():
    scene = load_scene(PREVIEW / "testPreviewSurfaceOpacityThreshold.usda")
    # Six references to an inactive prototype quad (default scheme catmullClark: a planar cage is
    # refined once), translated 1.5 apart in x.
    assert scene.geometry.num_triangles == 6 * 8
    minima = [scene.geometry.positions[scene.geometry.object_ids == i].reshape(-1, 3).min(0)[0] for i in range(6)]
    np.testing.assert_allclose(minima, 1.5 * np.arange(6), atol=1e-6)
    assert len({int(i) for i in scene.geometry.material_ids}) == 6
    assert all(o.double_sided for o in scene.objects)

    scene = load_scene(PREVIEW / "testPreviewSurfaceTranslucent.usda")
    cube = [i for i, o in enumerate(scene.objects) if o.path.endswith("MyCube2")]
    corners = scene.geometry.positions[scene.geometry.object_ids == cube[0]].reshape(-1, 3)
    np.testing.assert_allclose(corners.min(0), [0, -1, -4], atol=1e-6)  # size-2 cube at (1, 0, -3)
    np.testing.assert_allclose(corners.max(0), [2, 1, -2], atol=1e-6)


def _run_info(argv: list[str]) -> int:
    """`relight info ARGV` through the subcommand's own parser (as `pipeline.cli` registers it)."""
    parser = argparse.ArgumentParser()
    info.add_parser(parser.add_subparsers())
    args = parser.parse_args(["info", *argv])
    return args.run(args)


def test_describe_stage_and_the_info_command(capsys):
    text = describe_stage(TEAPOT_SHOT)
    assert "triangles: 158210" in text
    assert "objects: 2" in text
    assert "lights: 2 (1 RectLight, 1 SphereLight)" in text
    assert "cameras: 1" in text and "/Shot/Cam  640x480" in text
    assert _run_info([str(TEAPOT_SHOT), "--width", "320", "--height", "240"]) == 0
    assert "/Shot/Cam  320x240" in capsys.readouterr().out
    with pytest.raises(RelightError, match="/Shot/Cam"):
        _run_info([str(TEAPOT_SHOT), "--camera", "/Nope"])


def test_describe_an_empty_stage(tmp_path):
    path = tmp_path / "empty.usda"
    path.write_text("#usda 1.0\n")
    text = describe_stage(path)
    assert "triangles: 0" in text and "cameras: 0" in text
