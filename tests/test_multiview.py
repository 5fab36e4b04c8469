"""Moving-camera relighting (Kim, Kyung & Lee 2009) end to end on the Cornell box: bake, novel views, CLI.

One small multiview bake (4,000 surface samples, caching images up to 128 px) is shared by the
module. Novel views are compared with `PathTracer(max_bounces=0)`; failing image tests write
relit / reference / error EXRs under tmp_path.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from pxr import Gf, Sdf, Usd, UsdGeom

from pipeline.bake.multiview.bake import bake_multiview, coverage_summary
from pipeline.bake.multiview.frames import FrameRenderer
from pipeline.bake.multiview.placement import PlacementSettings
from pipeline.bake.multiview.view import view_points
from pipeline.benchmarks.bench.measure import moved
from pipeline.cli import build_parser, main
from pipeline.reference.path_tracer import PathTracer, ReferenceSettings
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES
from relight_torch import open_cache
from relight_torch.cache.layer import read_cache_layer
from relight_torch.direct.relighter import Relighter
from relight_torch.io.exr import read_rgb_exr, write_rgb_exr
from relight_torch.light_samples import fixed_light_samples
from relight_torch.metrics import psnr
from relight_torch.multiview.incident import group_images, incident_table, view_directions
from relight_torch.multiview.relighter import MultiviewRelighter
from relight_torch.multiview.views import camera_column, gather_gbuffer
from relight_torch.parallel import torch_threads

WIDTH, HEIGHT = 64, 48
SETTINGS = PlacementSettings(
    coverage=0.05,
    num_samples=4000,
    patience=10,
    max_resolution=128,
    min_resolution=32,
    grid_size=32,
    num_rays=16,
    max_secondary=8,
)
# Measured on the moved view below (64x48, 2x2 sub-samples): 44.0 dB with small holes filled and the
# large ones left black, 44.2 dB with them baked on demand; 5.5 % of its sub-samples are holes,
# mostly along silhouettes and in the blocks' shadowed corners. The shot camera's own view: 40.2 dB.
PSNR_FILLED, PSNR_PATCHED, MAX_HOLES = 41.0, 41.0, 0.08
# A moved view's image from the cached lighting against the same view's GBuffer re-traced by the
# direct Relighter: measured 54.4 and 50.2 dB on the two views of test_camera_move_traces_no_shadow_rays
# without edge refinement; the second view with it (contrast 0.8) 50.5 dB, its edge points 2.1 % of
# points x lights.
PSNR_RETRACED = 47.0
PSNR_RETRACED_EDGES, MAX_EDGES = 47.0, 0.05
# The same view with near-field refinement alone (0.1): 50.3 dB, its near-field points 4.0 % of points x lights.
MAX_NEAR = 0.08


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    directory = tmp_path_factory.mktemp("multiview")
    shot = SCENES["cornell_box"].write(directory)
    scene = load_scene(shot, width=WIDTH, height=HEIGHT)
    camera = find_camera(scene, SCENES["cornell_box"].camera)
    layer = bake_multiview(scene, camera, directory / "cache", "cornell", supersampling=2, settings=SETTINGS)
    return scene, camera, layer


def _moved(camera, scene, shift=(0.12, 0.06, -0.1), yaw_degrees=8.0):
    """The camera moved by `shift` x the scene's extent and turned about +Y."""
    lo, hi = scene.bounds
    angle = np.radians(yaw_degrees)
    turn = np.eye(4)
    turn[[0, 0, 2, 2], [0, 2, 0, 2]] = np.cos(angle), np.sin(angle), -np.sin(angle), np.cos(angle)
    matrix = camera.world_from_camera @ turn
    matrix[:3, 3] += np.array(shift) * (hi - lo)
    return dataclasses.replace(camera, world_from_camera=matrix, path="/Test/Moved")


def _reference(scene, camera):
    return PathTracer(scene, ReferenceSettings(spp=64, max_bounces=0, seed=3)).render(camera).mean


def test_bake_records_caching_cameras_and_coverage(baked):
    _scene, _, layer = baked
    description = read_cache_layer(layer)
    parameters = description.parameters
    assert description.method == "multiview"
    table = np.load(layer.parent / "cornell.cameras.npy", allow_pickle=False)
    assert parameters["numViews"] == table.shape[0] == sum(p.name.startswith("view") for p in description.payloads)
    assert parameters["numPrimary"] >= 1
    half_width = camera_column(table, "horizontalAperture") / 2 / camera_column(table, "focalLength")
    fov = np.degrees(2 * np.arctan(half_width))
    assert np.all(fov <= 120.0 + 1e-6)
    # Primary faces are 90 degrees; the loop stops under the threshold or at the camera budget.
    assert np.allclose(fov[camera_column(table, "kind") == 0], 90.0)
    assert parameters["uncoveredFraction"] < SETTINGS.coverage or parameters["numSecondary"] == SETTINGS.max_secondary
    assert parameters["primaryFraction"] > 0.5
    assert set(camera_column(table, "width")) <= {32.0, 64.0, 128.0}
    assert coverage_summary(layer).startswith(f"{parameters['numViews']} caching views")
    # Each caching view's EXR records its own size, so the generic payload checks of `relight info` pass.
    assert all(
        p.shape == (camera_column(table, "height")[int(p.name[4:])], camera_column(table, "width")[int(p.name[4:])])
        for p in description.payloads
        if p.name.startswith("view")
    )
    assert main(["info", str(layer)]) == 0


def test_novel_view_matches_reference(baked, tmp_path):
    scene, camera, layer = baked
    relighter = open_cache(layer)
    assert isinstance(relighter, MultiviewRelighter)
    moved = _moved(camera, scene)
    reference = _reference(scene, moved)
    frames = FrameRenderer(relighter), FrameRenderer(relighter, fill_holes=True)
    filled, patched = (renderer.render(moved) for renderer in frames)
    report = filled.report
    assert report.num_points > 0.5 * WIDTH * HEIGHT
    assert report.hole_fraction_after <= report.hole_fraction_before < MAX_HOLES
    values = psnr(filled.image, reference), psnr(patched.image, reference)
    if values[0] < PSNR_FILLED or values[1] < PSNR_PATCHED:
        for label, image in (("filled", filled.image), ("patched", patched.image), ("reference", reference)):
            write_rgb_exr(tmp_path / f"{label}.exr", image)
    assert values[0] >= PSNR_FILLED and values[1] >= max(PSNR_PATCHED, values[0] - 0.1), (
        f"PSNR {values}; images in {tmp_path}"
    )
    if report.num_large_holes:
        assert patched.patched_pixels > 0


def test_view_points_match_the_bake_of_the_same_camera(baked):
    """The shot camera's own view: every point finds a caching camera sample on its own object."""
    _, camera, layer = baked
    relighter = open_cache(layer)
    view = view_points(relighter.caster, relighter.occluder_objects, camera, relighter.supersampling)
    relighter.set_view(view)
    gbuffer = relighter.relighter.gbuffer
    assert gbuffer.num_samples >= view.num_points * 0.95
    assert np.all(np.einsum("nk,nk->n", gbuffer.normal.numpy(), gbuffer.geometric_normal.numpy()) > 0.5)


def _write_camera_layer(path, camera, scene, times=(1.0, 2.0)):
    """A lights layer that only adds an animated camera /World/NovelCam (the shot camera, sliding in x)."""
    stage = Usd.Stage.CreateNew(str(path))
    usd_camera = UsdGeom.Camera.Define(stage, "/World/NovelCam")
    usd_camera.CreateFocalLengthAttr(camera.focal_length)
    usd_camera.CreateHorizontalApertureAttr(camera.horizontal_aperture)
    usd_camera.CreateVerticalApertureAttr(camera.horizontal_aperture)
    op = usd_camera.AddTransformOp()
    lo, hi = scene.bounds
    for i, time in enumerate(times):
        matrix = camera.world_from_camera.copy()
        matrix[0, 3] += 0.1 * i * (hi - lo)[0]
        op.Set(Gf.Matrix4d(matrix.T.tolist()), Usd.TimeCode(time))
    stage.GetRootLayer().Save()
    return Sdf.Layer.FindOrOpen(str(path)).identifier


def test_render_cli_camera_from_lights_layer_over_time(baked, tmp_path):
    scene, camera, layer = baked
    lights = _write_camera_layer(tmp_path / "novel.usda", camera, scene)
    out = tmp_path / "frame.exr"
    assert (
        main(
            [
                "render",
                str(layer),
                "--camera",
                "/World/NovelCam",
                "--lights",
                lights,
                "--time",
                "1",
                "--time",
                "2",
                "-o",
                str(out),
            ]
        )
        == 0
    )
    first, second = (read_rgb_exr(tmp_path / f"frame.{t:04d}.exr") for t in (1, 2))
    assert first.shape == second.shape == (HEIGHT, WIDTH, 3)
    # At time 1 NovelCam is the shot camera: the same image as the Python API renders for it.
    relighter = open_cache(layer)
    expected = FrameRenderer(relighter).render(camera).image
    np.testing.assert_allclose(first, expected, atol=1e-3)
    assert np.abs(first - second).mean() > 1e-3
    assert main(["render", str(layer), "--camera", "/World/Missing", "-o", str(out)]) == 2
    # Without --camera a multiview cache renders its own camera (the shot camera, NovelCam at time 1).
    assert main(["render", str(layer), "-o", str(tmp_path / "own.exr")]) == 0
    np.testing.assert_allclose(read_rgb_exr(tmp_path / "own.exr"), first, atol=1e-3)


def test_render_cli_takes_a_camera_path_as_one_list_of_times():
    parse = build_parser().parse_args
    assert parse(["render", "c.relight.usda", "--time", "1", "2", "--time", "3.5", "-o", "f.exr"]).time == [
        1.0,
        2.0,
        3.5,
    ]
    assert parse(["render", "c.relight.usda", "-o", "f.exr"]).time is None


def test_bake_cli_refuses_an_empty_box(tmp_path):
    shot = SCENES["cornell_box"].write(tmp_path)
    assert (
        main(
            [
                "bake",
                str(shot),
                "--camera",
                SCENES["cornell_box"].camera,
                "--method",
                "multiview",
                "--box",
                "0",
                "0",
                "0",
                "0",
                "1",
                "1",
                "-o",
                str(tmp_path / "out"),
            ]
        )
        == 2
    )
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").glob("*.relight.usda"))


def _caching_view_gbuffer(views, k):
    """Caching camera k's own deep framebuffer, from the pool (its pixels and camera position)."""
    rows = torch.nonzero(views.pool_view == k).squeeze(-1)
    height, width = (int(v) for v in views.sizes[k])
    pixel = views.pool_pixel[rows]
    return dataclasses.replace(
        gather_gbuffer(views.pool, rows),
        image_size=(height, width),
        pixel_index=pixel[:, 1].long() * width + pixel[:, 0].long(),
        camera_position=views.centres[:, k].clone(),
    )


def test_cached_lighting_per_sample_equals_the_direct_relighter(baked):
    """One group per light sample: the cached lighting of a caching view, shaded at that view, is the
    direct Relighter's (shadow rays, rect-light ratio estimator, BRDF) on its deep framebuffer."""
    relighter = open_cache(baked[2])
    gbuffer = _caching_view_gbuffer(relighter.views, 0)
    direct = Relighter(gbuffer, relighter.visibility, 1, 1.0, relighter.settings, relighter.object_paths)
    direct.set_lights(relighter.lights)
    direct.render()
    shadowed = 0
    for light in relighter.lights:
        samples = direct.num_light_samples(light)
        u = fixed_light_samples(gbuffer.num_samples, samples)
        table, unshadowed = incident_table(
            light, gbuffer.position, gbuffer.geometric_normal, gbuffer.normal, u, relighter.visibility, samples
        )
        # The unshadowed sum (what edge detection divides by) is the table of the light without shadows.
        unlit, _ = incident_table(
            dataclasses.replace(light, shadow=dataclasses.replace(light.shadow, enable=False)),
            gbuffer.position,
            gbuffer.geometric_normal,
            gbuffer.normal,
            u,
            relighter.visibility,
            1,
        )
        torch.testing.assert_close(unshadowed, unlit[..., :3].sum((1, 2)))
        assert bool((table[..., :3].sum((1, 2)) <= unshadowed * (1 + 1e-5)).all())
        shadowed += int((table[..., :3].sum((1, 2)) < 0.5 * unshadowed).sum())
        images = group_images(
            gbuffer.params,
            view_directions(gbuffer.wo_world(), gbuffer.normal, gbuffer.geometric_normal),
            table.permute(2, 1, 0),
        )
        expected = direct.unit_images(light.path)
        assert float(expected.abs().max()) > 0
        torch.testing.assert_close(images, expected, rtol=1e-4, atol=1e-5 * float(expected.abs().max()))
    assert shadowed > 0  # the unshadowed sums were compared where shadows matter


def test_lights_shaded_on_two_threads_give_the_images_of_one(baked):
    # A view's lights are shaded on the kept worker threads, one light each: the image and the
    # counters (lit caching samples, edge points) are those of the lights in turn.
    scene, camera, layer = baked
    images, counters = [], []
    for threads in (1, 2):
        with torch_threads(threads):
            relighter = open_cache(layer)
            (light,) = relighter.lights
            relighter.set_light(dataclasses.replace(moved(light, 0.05), path="/Test/Second"))
            images.append(FrameRenderer(relighter).render(_moved(camera, scene)).image)
        counters.append(dict(relighter.counters))
    assert counters[1] == counters[0] and counters[0]["edge_samples"] > 0
    np.testing.assert_allclose(images[1], images[0], rtol=1e-5, atol=1e-6)


def test_camera_move_traces_no_shadow_rays(baked):
    """Once the caching samples are lit, moving the camera traces nothing (edge refinement off) and
    matches re-tracing the new view; with it, only the points on a light's edges are traced; a light
    move re-traces only that light, at the caching samples the view uses."""
    scene, camera, layer = baked
    relighter = open_cache(layer)
    relighter.edge_contrast = relighter.near_field = None
    relighter.prepare_lighting()
    rays, lit = relighter.visibility.num_rays, relighter.counters["lit_samples"]
    assert lit == relighter.views.pool.num_samples * len(relighter.lights)
    renderer = FrameRenderer(relighter)
    for shift in ((0.12, 0.06, -0.1), (-0.1, 0.0, -0.15)):
        image = renderer.render(_moved(camera, scene, shift)).image
        assert relighter.visibility.num_rays == rays and relighter.counters["lit_samples"] == lit
        retraced = Relighter(
            relighter.relighter.gbuffer,
            relighter.visibility,
            relighter.supersampling,
            relighter.exposure_scale,
            relighter.settings,
            relighter.object_paths,
        )
        retraced.set_lights(relighter.lights)
        expected = retraced.render().numpy()
        # The same estimator, sampled at the nearest caching pixel with one BRDF evaluation per light
        # instead of at the point itself (see PSNR_RETRACED).
        assert psnr(image, expected) > PSNR_RETRACED, psnr(image, expected)
        rays = relighter.visibility.num_rays  # re-tracing counted its rays
    # Edge refinement (the default): the points on a light's edges in the caching images are traced.
    relighter.edge_contrast = 0.8
    image = renderer.render(_moved(camera, scene, shift)).image
    edges = relighter.counters["edge_samples"]
    assert 0 < edges < MAX_EDGES * relighter.report.num_points * len(relighter.lights)
    assert rays < relighter.visibility.num_rays <= rays + edges * relighter.settings.area_samples
    # Edge points' light samples: the first rows of one kept draw, equal to a draw of that many.
    assert torch.equal(relighter._point_samples(7, 16), fixed_light_samples(7, 16, relighter.settings.seed))
    assert psnr(image, expected) > PSNR_RETRACED_EDGES, psnr(image, expected)
    # Near-field refinement: the points far from their caching sample for their distance to the light.
    relighter.edge_contrast, relighter.near_field = None, 0.1
    rays, before = relighter.visibility.num_rays, relighter.counters["edge_samples"]
    image = renderer.render(_moved(camera, scene, shift)).image
    near = relighter.counters["edge_samples"] - before
    assert 0 < near < MAX_NEAR * relighter.report.num_points * len(relighter.lights)
    assert psnr(image, expected) > PSNR_RETRACED_EDGES, psnr(image, expected)
    assert rays < relighter.visibility.num_rays <= rays + near * relighter.settings.area_samples
    rays = relighter.visibility.num_rays
    relighter.near_field = None
    light = relighter.lights[0]
    relighter.set_light(dataclasses.replace(light, intensity=2.0 * light.intensity))
    relighter.render()
    assert relighter.visibility.num_rays == rays  # a colour edit keeps the cached lighting
    matrix = light.world_from_light.copy()
    matrix[:3, 3] += 0.02 * (scene.bounds[1] - scene.bounds[0])
    relighter.set_light(dataclasses.replace(light, world_from_light=matrix))
    relighter.render()
    used = torch.unique(relighter._view.rows).numel()
    assert relighter.visibility.num_rays > rays and relighter.counters["lit_samples"] == lit + used
