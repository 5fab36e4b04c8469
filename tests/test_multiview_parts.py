"""The parts of the multiview method: projection, eq. 5 against its slow twin, hole filling,
maximal spheres, importance sampling, resampling taps and material columns, BRDF groups (no full
bake)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from pxr import Usd

from pipeline.bake.deep_framebuffer import bake_deep_framebuffer
from pipeline.bake.multiview.cameras import (
    CUBE_FORWARD,
    camera_from_row,
    camera_row,
    look_camera,
    resolution_from_coverage,
)
from pipeline.bake.multiview.placement import CUBE_UP
from pipeline.bake.multiview.samples import SurfaceSamples, object_importance, sample_surfaces
from pipeline.bake.multiview.spheres import maximal_spheres
from pipeline.bake.multiview.view import view_points
from pipeline.scene import find_camera, load_scene
from pipeline.scene.camera import project
from pipeline.scenes import SCENES
from pipeline.tracing import Tracer
from relight_torch.multiview.correspondence import (
    MAX_SLOPE,
    RELATIVE_DEPTH_TOLERANCE,
    Correspondence,
    ViewPoints,
    correspondence_map,
)
from relight_torch.multiview.holes import fill_small_holes
from relight_torch.multiview.incident import group_images, view_directions
from relight_torch.multiview.resample import bilinear_samples
from relight_torch.multiview.views import (
    CONSTANT,
    PER_MATERIAL,
    PRIMARY,
    SAME_SURFACE_COS,
    SECONDARY,
    TEXTURED,
    CachingViews,
    camera_column,
    column_kinds,
    world_from_camera,
)


@pytest.fixture(scope="module")
def cornell(tmp_path_factory):
    shot = SCENES["cornell_box"].write(tmp_path_factory.mktemp("cornell"))
    scene = load_scene(shot, width=32, height=24)
    return shot, scene, Tracer(scene.geometry)


@pytest.fixture(scope="module")
def views(cornell):
    """Three small caching cameras inside the Cornell box and their deep framebuffers."""
    _, scene, tracer = cornell
    lo, hi = scene.bounds
    centre = (lo + hi) / 2
    cameras = [
        look_camera("/C/0", centre, (0, 0, 1), (0, 1, 0), 90.0, 24, 1.0, 2000.0),
        look_camera("/C/1", centre + [150, 100, -150], (-1, -1, 1), (0, 1, 0), 100.0, 32, 1.0, 2000.0),
        look_camera("/C/2", centre + [-180, -120, 0], (1, -0.3, 0.5), (0, 1, 0), 60.0, 16, 1.0, 2000.0),
    ]
    table = np.stack([camera_row(c, PRIMARY if i == 0 else SECONDARY, i) for i, c in enumerate(cameras)])
    gbuffers = [bake_deep_framebuffer(scene, c, 1, 1, tracer).gbuffer for c in cameras]
    return CachingViews.build(table, gbuffers), cameras


def test_camera_rows_round_trip_and_project_as_the_pipeline_does(views):
    caching, cameras = views
    rng = np.random.default_rng(0)
    points = rng.uniform(0, 550, (500, 3))
    for k, camera in enumerate(cameras):
        again = camera_from_row(caching.table[k], camera.path)
        np.testing.assert_allclose(again.world_from_camera, camera.world_from_camera)
        expected_pixels, expected_depth = project(camera, points)
        pixels, depth = caching.project(k, torch.from_numpy(points))
        np.testing.assert_allclose(depth.numpy(), expected_depth, rtol=1e-9)
        front = expected_depth > 0
        np.testing.assert_allclose(pixels.numpy()[front], expected_pixels[front], rtol=1e-7, atol=1e-6)
        assert np.isnan(pixels.numpy()[~front]).all()


def _matches_slow_twin(caching: CachingViews, cornell, count: int):
    """`correspondence_map` of `count` points of the Cornell shot against the slow twin; the fast one."""
    _, scene, tracer = cornell
    view = view_points(tracer, scene.geometry.object_ids, find_camera(scene, SCENES["cornell_box"].camera))
    pick = torch.from_numpy(np.random.default_rng(1).choice(view.num_points, count, replace=False))
    position, normal, objects = view.position[pick], view.geometric_normal[pick], view.object_id[pick]
    fast = correspondence_map(caching, position, normal, objects)
    slow = _correspondence_loop(caching, position.numpy(), normal.numpy(), objects.numpy())
    # float32 against float64: scores may tie within rounding, so compare where they are distinct.
    distinct = (fast.score - slow.score).abs() <= 1e-5 * slow.score.abs()
    assert distinct.float().mean() > 0.98
    assert torch.equal(fast.pool_row[distinct], slow.pool_row[distinct])
    assert torch.equal(fast.view[distinct], slow.view[distinct])
    return fast


def test_correspondence_map_matches_its_slow_twin(cornell, views):
    caching, _ = views
    fast = _matches_slow_twin(caching, cornell, 150)
    assert 0.3 < float(fast.covered.float().mean()) < 1.0  # both covered and uncovered points are exercised


def test_a_cube_is_scored_through_the_face_a_point_lies_in(cornell):
    """An omni-directional camera (five faces: the floor's dropped) and a single camera: the map
    scores the cube once, through the face of each point's direction, and still equals the twin's
    camera-by-camera maximum."""
    _, scene, tracer = cornell
    centre = (scene.bounds[0] + scene.bounds[1]) / 2
    faces = [
        look_camera(f"/Cube/{f}", centre, CUBE_FORWARD[f], CUBE_UP[f], 90.0, 16, 1.0, 2000.0) for f in (0, 1, 2, 4, 5)
    ]
    single = look_camera("/C/1", centre + [150, 100, -150], (-1, -1, 1), (0, 1, 0), 100.0, 32, 1.0, 2000.0)
    table = np.stack([camera_row(c, PRIMARY, 0) for c in faces] + [camera_row(single, SECONDARY, 0)])
    caching = CachingViews.build(
        table, [bake_deep_framebuffer(scene, c, 1, 1, tracer).gbuffer for c in faces + [single]]
    )
    assert caching.cubes.tolist() == [[0, 1, 2, -1, 3, 4]] and caching.singles.tolist() == [5]
    fast = _matches_slow_twin(caching, cornell, 300)
    assert len(set(fast.view[fast.covered].tolist())) >= 4  # several faces and the single camera chosen


def _grid_view(height, width, holes):
    """A (height, width) view on one plane z = 0 facing +z, every pixel covered, `holes` flat pixels unmatched."""
    index = torch.arange(height * width)
    rows = index.clone()
    rows[holes] = -1
    position = torch.stack([index % width, index // width, torch.zeros_like(index)], -1).float()
    normal = torch.tensor([[0.0, 0.0, 1.0]]).expand(height * width, 3)
    view = ViewPoints(
        (height, width),
        index,
        position,
        normal,
        torch.zeros(height * width, dtype=torch.int64),
        torch.ones(height * width),
        torch.tensor([0.0, 0.0, 10.0]),
    )
    return view, rows


def test_small_holes_are_filled_from_neighbours_and_large_ones_reported(views):
    caching, _ = views
    pool = caching.pool
    height, width = 8, 10
    single, pair = [2 * width + 2], [5 * width + 1, 5 * width + 2]
    block = [r * width + c for r in range(1, 4) for c in range(6, 9)]
    view, rows = _grid_view(height, width, torch.tensor(single + pair + block))
    # Every pool row used here: on object 0 facing +z, except row 11 (another object).
    pool = pool.__class__(
        **{
            **pool.__dict__,
            "object_id": torch.zeros(pool.num_samples, dtype=torch.int32),
            "geometric_normal": torch.tensor([[0.0, 0.0, 1.0]]).expand(pool.num_samples, 3),
        }
    )
    pool.object_id[11] = 5
    filled, report = fill_small_holes(view, rows, pool)
    assert report.num_holes == 12 and report.num_large_holes == 1 and report.num_filled == 3
    assert sorted(report.large_pixel_index.tolist()) == block
    assert int(filled[single[0]]) in {
        single[0] + d for d in (-width - 1, -width, -width + 1, -1, 1, width - 1, width, width + 1)
    }
    assert filled[single[0]] != 11 and (filled[block] == -1).all()
    assert report.hole_fraction_before == pytest.approx(12 / 80) and report.hole_fraction_after == pytest.approx(9 / 80)


def _cube_samples(count: int, rng) -> SurfaceSamples:
    """Samples on the inside of the unit cube's six faces, normals pointing in."""
    axis = rng.integers(0, 3, count)
    side = rng.integers(0, 2, count)
    position = rng.random((count, 3))
    position[np.arange(count), axis] = side
    normal = np.zeros((count, 3))
    normal[np.arange(count), axis] = 1 - 2 * side
    return SurfaceSamples(
        position.astype(np.float32), normal.astype(np.float32), np.ones(count), np.zeros(count, np.int32)
    )


def test_maximal_sphere_of_an_empty_cube_is_its_inscribed_sphere():
    rng = np.random.default_rng(2)
    samples = _cube_samples(6000, rng)
    spheres = maximal_spheres(samples, np.full(3, -0.5), np.full(3, 1.5), 0.02, patience=4, rng=rng)
    assert spheres, "no sphere found"
    best = spheres[0]
    np.testing.assert_allclose(best.centre, 0.5, atol=0.06)
    assert 0.44 < best.radius <= 0.5


def test_importance_attribute_weights_the_samples(cornell, tmp_path):
    shot, _scene, _ = cornell
    layer = Usd.Stage.Open(str(shot))
    tall = layer.GetPrimAtPath("/World/Geometry/TallBlock")
    tall.ApplyAPI("RelightImportanceAPI")
    tall.GetAttribute("relight:importance").Set(0.0)
    layer.GetRootLayer().Export(str(tmp_path / "weighted.usda"))
    weighted = load_scene(tmp_path / "weighted.usda", width=32, height=24)
    importance = object_importance(weighted)
    paths = [obj.path for obj in weighted.objects]
    assert importance[paths.index("/World/Geometry/TallBlock")] == 0.0 and importance.sum() == len(paths) - 1
    samples = sample_surfaces(weighted, 2000, np.random.default_rng(0), importance)
    assert paths.index("/World/Geometry/TallBlock") not in set(samples.object_id.tolist())
    assert resolution_from_coverage(1.0, 32, 256) == 256 and resolution_from_coverage(0.01, 32, 256) == 32


def test_bilinear_resampling_is_exact_at_pixel_centres_and_blends_between(views):
    caching, _ = views
    pool = caching.pool
    # Pool rows of view 0 (pixel-centred) whose right-hand neighbour is a sample of the same surface.
    rows = torch.nonzero(caching.pool_view == 0).squeeze(-1)
    centre = caching.pool_pixel[rows]
    right = caching.pool_row[
        (centre[:, 1] - 0.5).long() * int(caching.sizes[0, 1])
        + (centre[:, 0] + 0.5).long().clamp(max=int(caching.sizes[0, 1]) - 1)
    ]
    ok = (
        (right >= 0)
        & (pool.object_id[right.clamp(min=0)] == pool.object_id[rows])
        & ((pool.geometric_normal[right.clamp(min=0)] * pool.geometric_normal[rows]).sum(-1) > 0.99)
        & (centre[:, 0] + 1 < int(caching.sizes[0, 1]))
    )
    rows, right, centre = rows[ok][:50], right[ok][:50], centre[ok][:50]
    assert rows.numel() == 50
    at_centre = bilinear_samples(caching, centre, rows, pool.geometric_normal[rows])
    torch.testing.assert_close(at_centre.params.diffuse_color, pool.params.diffuse_color[rows])
    torch.testing.assert_close(at_centre.normal, pool.normal[rows], atol=1e-5, rtol=1e-5)
    between = bilinear_samples(caching, centre + torch.tensor([0.5, 0.0]), rows, pool.geometric_normal[rows])
    expected = 0.5 * (pool.params.diffuse_color[rows] + pool.params.diffuse_color[right])
    torch.testing.assert_close(between.params.diffuse_color, expected, atol=1e-5, rtol=1e-5)


def _block_taps(caching, view_index, pixel, object_id, normal):
    """The 2 x 2 caching pixels around `pixel` (N, 2) in cameras `view_index` (N,), kept where the
    same surface as the points (object, geometric normal): a direct (slow) twin of the resampling
    taps, as (N, 4) pool rows (-1 where not kept) and bilinear weights renormalised over those kept."""
    taps, weights = [], []
    for k, (x, y), obj, n in zip(view_index.tolist(), pixel.tolist(), object_id.tolist(), normal, strict=True):
        height, width = (int(v) for v in caching.sizes[k])
        bx, by = int(np.floor(x - 0.5)), int(np.floor(y - 0.5))
        fx, fy = x - 0.5 - bx, y - 0.5 - by
        row_taps, row_weights = [], []
        for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
            cx, cy = bx + dx, by + dy
            row = (
                int(caching.pool_row[caching.image_offsets[k] + cy * width + cx])
                if (0 <= cx < width and 0 <= cy < height)
                else -1
            )
            same = (
                row >= 0
                and int(caching.pool.object_id[row]) == obj
                and float(caching.pool.geometric_normal[row] @ n) > 0.7
            )
            row_taps.append(row if same else -1)
            row_weights.append((fx if dx else 1 - fx) * (fy if dy else 1 - fy) if same else 0.0)
        total = sum(row_weights)
        taps.append(row_taps)
        weights.append([w / total for w in row_weights])
    return torch.tensor(taps), torch.tensor(weights)


def test_resampling_taps_from_the_neighbour_table_equal_the_pixel_block(cornell, views):
    """The taps read from `CachingViews.neighbours` are the 2 x 2 block of same-surface caching pixels
    around each point's projection, with the same bilinear weights."""
    _, scene, tracer = cornell
    caching, _ = views
    camera = find_camera(scene, SCENES["cornell_box"].camera)
    view = view_points(tracer, scene.geometry.object_ids, camera)
    found = correspondence_map(caching, view.position, view.geometric_normal, view.object_id)
    covered = torch.nonzero(found.covered).squeeze(-1)
    pick = covered[torch.from_numpy(np.random.default_rng(2).choice(covered.numel(), 300, replace=False))]
    pixel, rows, normal = found.pixel[pick], found.pool_row[pick], view.geometric_normal[pick]
    resampled = bilinear_samples(caching, pixel, rows, normal)
    taps, weights = _block_taps(caching, found.view[pick], pixel, view.object_id[pick], normal)
    for got_taps, got_weights, want_taps, want_weights in zip(
        resampled.taps, resampled.weights, taps, weights, strict=True
    ):
        used = want_weights > 0
        assert set(got_taps[got_weights > 0].tolist()) == set(want_taps[used].tolist())
        assert torch.allclose(got_weights.sort().values, want_weights.sort().values, atol=1e-5)
    assert (weights > 0).sum(-1).float().mean() > 2.0  # blends are exercised, not only single taps


def test_material_columns_by_kind_and_frames_without_cached_tangents(views):
    """Packed material columns are classed constant / per material / textured; resampled frames are
    orthonormal from the normal alone (zero cached tangents, as meshes without UVs have, do not matter)."""
    packed = torch.tensor([[1.0, 2.0, 5.0], [1.0, 2.0, 6.0], [1.0, 3.0, 7.0]])
    assert column_kinds(packed, torch.tensor([0, 0, 1])).tolist() == [CONSTANT, PER_MATERIAL, TEXTURED]
    caching, _ = views
    pool = caching.pool
    rows = torch.arange(0, pool.num_samples, 7)
    bare = dataclasses.replace(caching, pool=dataclasses.replace(pool, tangent=torch.zeros_like(pool.tangent)))
    resampled = bilinear_samples(bare, caching.pool_pixel[rows], rows, pool.geometric_normal[rows])
    frame = torch.stack([resampled.tangent, resampled.bitangent, resampled.normal], -2)  # (N, 3, 3)
    torch.testing.assert_close(frame @ frame.transpose(-1, -2), torch.eye(3).expand_as(frame), atol=1e-5, rtol=0)
    torch.testing.assert_close(
        resampled.normal, torch.nn.functional.normalize(pool.normal[rows], dim=-1), atol=1e-5, rtol=0
    )
    for name in ("diffuse_color", "roughness", "metallic"):
        torch.testing.assert_close(getattr(resampled.params, name), getattr(pool.params, name)[rows])


def test_one_group_shading_equals_the_general_path(views):
    """`group_images` with one group (its light factored out of the BRDF sum) equals the general
    per-group sum (here with an unlit second group)."""
    caching, _ = views
    pool = caching.pool
    rows = torch.arange(0, pool.num_samples, 5)
    generator = torch.Generator().manual_seed(3)
    normal = pool.geometric_normal[rows]
    wo = torch.nn.functional.normalize(torch.rand(rows.numel(), 3, generator=generator) - 0.5 + normal, dim=-1)
    one = torch.cat(
        [
            torch.rand(3, 1, rows.numel(), generator=generator),
            torch.randn(3, 1, rows.numel(), generator=generator) + normal.T[:, None],
            torch.full((1, 1, rows.numel()), 0.7),
        ]
    )
    unlit = torch.cat([torch.zeros(3, 1, rows.numel()), normal.T[:, None], torch.full((1, 1, rows.numel()), 0.7)])
    args = (pool.params.index(rows), view_directions(wo, normal, normal))
    single = group_images(*args, one)
    assert float(single.abs().max()) > 0
    torch.testing.assert_close(single, group_images(*args, torch.cat([one, unlit], 1)), rtol=1e-5, atol=1e-6)


def _correspondence_loop(
    views: CachingViews, position: np.ndarray, normal: np.ndarray, object_id: np.ndarray
) -> Correspondence:
    """`correspondence_map` written from the formula: a Python loop over points and cameras."""
    table = views.table
    world = world_from_camera(table)
    sizes = views.sizes.cpu().numpy()
    offsets = views.image_offsets.cpu().numpy()
    cached_depth, pool_row = views.depth.cpu().numpy(), views.pool_row.cpu().numpy()
    pool_object, pool_normal = views.pool.object_id.cpu().numpy(), views.pool.geometric_normal.cpu().numpy()
    pixel_angle = views.pixel_angle.cpu().numpy()
    focal, h_ap, v_ap = (camera_column(table, n) for n in ("focalLength", "horizontalAperture", "verticalAperture"))
    h_off, v_off = camera_column(table, "horizontalApertureOffset"), camera_column(table, "verticalApertureOffset")
    view = np.full(len(position), -1, np.int64)
    rows = np.full(len(position), -1, np.int64)
    scores = np.zeros(len(position), np.float32)
    for i, (p, n) in enumerate(zip(np.asarray(position, np.float64), np.asarray(normal, np.float64), strict=True)):
        for k in range(len(table)):
            centre, axes = world[k][:3, 3], world[k][:3, :3]
            offset = centre - p
            d = np.linalg.norm(offset)
            cos = float(n @ offset / d)
            local = np.linalg.solve(axes, p - centre)
            depth = -local[2]
            if cos <= 0 or depth <= 0:
                continue
            height, width = sizes[k]
            x = ((focal[k] * local[0] / depth - h_off[k]) / h_ap[k] + 0.5) * width
            y = (0.5 - (focal[k] * local[1] / depth - v_off[k]) / v_ap[k]) * height
            if not (0 <= x < width and 0 <= y < height):
                continue
            pixel = offsets[k] + int(np.floor(y)) * width + int(np.floor(x))
            slope = min(np.sqrt(max(1 - cos * cos, 0.0)) / max(cos, 1 / MAX_SLOPE), MAX_SLOPE)
            tolerance = depth * (pixel_angle[k] * (1 + 2 * slope) + RELATIVE_DEPTH_TOLERANCE)
            if abs(depth - cached_depth[pixel]) > tolerance:
                continue
            sample = pool_row[pixel]
            if pool_object[sample] != object_id[i] or float(pool_normal[sample] @ n) <= SAME_SURFACE_COS:
                continue
            score = cos / (d * d) / float(pixel_angle[k]) ** 2
            if score > scores[i]:
                view[i], rows[i], scores[i] = k, sample, score
    return Correspondence(torch.from_numpy(view), torch.from_numpy(rows), torch.from_numpy(scores))
