"""Tests of pipeline.tracing: hand-computed hits, occlusion, ray offsets, and agreement with a slow
brute-force Moller-Trumbore twin."""

import gc
import warnings
import weakref

import numpy as np
import pytest

from pipeline.bake.direct.bake import bake_direct
from pipeline.bake.quality import measurement_window, resized
from pipeline.reference.path_tracer import PathTracer, ReferenceSettings
from pipeline.scene import find_camera, load_scene
from pipeline.scene.types import Geometry
from pipeline.scenes import SCENES
from pipeline.tracing import Tracer, shared_tracer
from relight_torch.visibility import embree


def make_geometry(positions, normals=None, uvs=None, material_ids=None, object_ids=None) -> Geometry:
    """A Geometry from (T, 3, 3) corners; default normals are the face normals, uvs zero,
    material ids 0..T-1 and object ids 100 + (0..T-1)."""
    positions = np.asarray(positions, np.float32)
    num_triangles = positions.shape[0]
    if normals is None:
        face = np.cross(positions[:, 1] - positions[:, 0], positions[:, 2] - positions[:, 0])
        face /= np.linalg.norm(face, axis=-1, keepdims=True)
        normals = np.repeat(face[:, None], 3, axis=1)
    return Geometry(
        positions=positions,
        normals=np.asarray(normals, np.float32),
        uvs=np.zeros((num_triangles, 3, 2), np.float32) if uvs is None else np.asarray(uvs, np.float32),
        material_ids=(
            np.arange(num_triangles, dtype=np.int32) if material_ids is None else np.asarray(material_ids, np.int32)
        ),
        object_ids=(
            100 + np.arange(num_triangles, dtype=np.int32) if object_ids is None else np.asarray(object_ids, np.int32)
        ),
    )


def rays(origins, directions):
    return np.asarray(origins, np.float32).reshape(-1, 3), np.asarray(directions, np.float32).reshape(-1, 3)


def unit(vector):
    vector = np.asarray(vector, np.float64)
    return vector / np.linalg.norm(vector)


# One triangle in the z = 0 plane, counter-clockwise seen from +z.
CORNERS = [[0, 0, 0], [2, 0, 0], [0, 2, 0]]
CORNER_NORMALS = [[0, 0, 1], unit([1, 0, 1]), unit([0, 1, 1])]
CORNER_UVS = [[0.1, 0.2], [0.9, 0.2], [0.1, 0.7]]


@pytest.fixture
def triangle_tracer():
    return Tracer(make_geometry([CORNERS], [CORNER_NORMALS], [CORNER_UVS], [3], [5]))


def test_triangle_hit_attributes_match_hand_computed_values(triangle_tracer):
    hits = triangle_tracer.intersect(*rays([0.5, 0.25, 3], [0, 0, -1]))
    # (0.5, 0.25) = 0.625 p0 + 0.25 p1 + 0.125 p2.
    weights = np.array([0.625, 0.25, 0.125])
    assert hits.hit.tolist() == [True]
    np.testing.assert_allclose(hits.distance, [3.0], rtol=1e-6)
    assert hits.triangle_id.tolist() == [0]
    np.testing.assert_allclose(hits.barycentrics, [[0.25, 0.125]], atol=1e-6)
    np.testing.assert_allclose(hits.position, [[0.5, 0.25, 0.0]], atol=1e-6)
    np.testing.assert_allclose(hits.geometric_normal, [[0, 0, 1]], atol=1e-6)
    np.testing.assert_allclose(hits.shading_normal, [unit(weights @ np.array(CORNER_NORMALS))], atol=1e-6)
    np.testing.assert_allclose(hits.uv, [weights @ np.array(CORNER_UVS)], atol=1e-6)
    assert hits.material_id.tolist() == [3]
    assert hits.object_id.tolist() == [5]
    for array, dtype in (
        (hits.distance, np.float32),
        (hits.triangle_id, np.int32),
        (hits.position, np.float32),
        (hits.material_id, np.int32),
    ):
        assert array.dtype == dtype


def test_distance_is_the_ray_parameter_and_normals_are_not_flipped(triangle_tracer):
    # From below, with a direction of length 2: t = 2 / 2; the normal still follows the winding.
    hits = triangle_tracer.intersect(*rays([0.5, 0.25, -2], [0, 0, 2]))
    np.testing.assert_allclose(hits.distance, [1.0], rtol=1e-6)
    np.testing.assert_allclose(hits.geometric_normal, [[0, 0, 1]], atol=1e-6)


def test_geometric_normal_follows_the_winding():
    reversed_corners = [CORNERS[0], CORNERS[2], CORNERS[1]]
    hits = Tracer(make_geometry([reversed_corners])).intersect(*rays([0.5, 0.25, 3], [0, 0, -1]))
    np.testing.assert_allclose(hits.geometric_normal, [[0, 0, -1]], atol=1e-6)
    # Corners 1 and 2 swapped, so are u and v.
    np.testing.assert_allclose(hits.barycentrics, [[0.125, 0.25]], atol=1e-6)


def test_shading_normal_falls_back_to_the_face_normal_where_corner_normals_cancel():
    normals = [[0, 0, 1], [0, 0, -1], [0, 0, 1]]
    tracer = Tracer(make_geometry([CORNERS], [normals]))
    # At (1, 0.5): weights (0.25, 0.5, 0.25), so the interpolated normal is exactly zero.
    hits = tracer.intersect(*rays([1, 0.5, 1], [0, 0, -1]))
    np.testing.assert_allclose(hits.shading_normal, [[0, 0, 1]])


def test_misses_hold_minus_one_inf_and_zeros(triangle_tracer):
    # Pointing away; passing beside the triangle; stopped by t_far before reaching it.
    origins, directions = rays([[0.5, 0.25, 3], [3, 3, 3], [0.5, 0.25, 3]], [[0, 0, 1], [0, 0, -1], [0, 0, -1]])
    hits = triangle_tracer.intersect(origins, directions, np.array([10, 10, 2.9], np.float32))
    assert not hits.hit.any()
    assert np.isinf(hits.distance).all()
    assert (hits.triangle_id == -1).all()
    assert (hits.material_id == -1).all() and (hits.object_id == -1).all()
    for array in (hits.barycentrics, hits.position, hits.geometric_normal, hits.shading_normal, hits.uv):
        assert (array == 0).all()


def test_t_far_is_not_modified(triangle_tracer):
    t_far = np.array([10.0], np.float32)
    triangle_tracer.intersect(*rays([0.5, 0.25, 3], [0, 0, -1]), t_far)
    assert t_far.tolist() == [10.0]


def test_occlusion_depends_on_t_far_around_the_blocker(triangle_tracer):
    origins, directions = rays([[0.5, 0.25, 3]] * 3, [[0, 0, -1]] * 2 + [[0, 0, 1]])
    t_far = np.array([2.999, 3.001, 100.0], np.float32)
    assert triangle_tracer.occluded(origins, directions, t_far).tolist() == [False, True, False]


def test_empty_batches_and_empty_geometry(triangle_tracer):
    no_rays = np.zeros((0, 3), np.float32)
    hits = triangle_tracer.intersect(no_rays, no_rays)
    assert hits.num_rays == 0 and hits.position.shape == (0, 3) and hits.uv.shape == (0, 2)
    assert triangle_tracer.occluded(no_rays, no_rays, np.zeros(0, np.float32)).shape == (0,)

    empty = Tracer(make_geometry(np.zeros((0, 3, 3))))
    origins, directions = rays([0, 0, 1], [0, 0, -1])
    hits = empty.intersect(origins, directions)
    assert hits.triangle_id.tolist() == [-1] and hits.material_id.tolist() == [-1]
    assert (hits.position == 0).all()
    assert empty.occluded(origins, directions, np.array([10], np.float32)).tolist() == [False]


@pytest.mark.parametrize(
    "origins, directions, t_far, message",
    [
        (np.zeros((2, 3)), np.zeros((2, 3), np.float32), None, "origins must be float32"),
        (np.zeros((2, 3), np.float32), np.zeros((3, 3), np.float32), None, "directions must be"),
        (np.zeros((2, 4), np.float32), np.zeros((2, 4), np.float32), None, r"\(2, 4\)"),
        (np.zeros((2, 3), np.float32), np.zeros((2, 3), np.float32), np.zeros(3, np.float32), "t_far must be"),
    ],
)
def test_bad_ray_arrays_raise_naming_the_shape(triangle_tracer, origins, directions, t_far, message):
    with pytest.raises(ValueError, match=message):
        triangle_tracer.intersect(origins, directions, t_far)


def test_occluded_requires_t_far(triangle_tracer):
    with pytest.raises(ValueError, match="t_far is required"):
        triangle_tracer.occluded(*rays([0, 0, 1], [0, 0, -1]), None)


def test_bad_geometry_raises_naming_the_array():
    geometry = make_geometry([CORNERS])
    with pytest.raises(ValueError, match=r"Geometry\.uvs"):
        Tracer(
            Geometry(
                geometry.positions,
                geometry.normals,
                np.zeros((1, 3, 3), np.float32),
                geometry.material_ids,
                geometry.object_ids,
            )
        )


# A unit cube, two counter-clockwise (seen from outside) triangles per face; material id = face.
CUBE_FACES = {  # outward normal: the face's corners, counter-clockwise seen from outside
    (1, 0, 0): [(1, 0, 0), (1, 1, 0), (1, 1, 1), (1, 0, 1)],
    (-1, 0, 0): [(0, 0, 0), (0, 0, 1), (0, 1, 1), (0, 1, 0)],
    (0, 1, 0): [(0, 1, 0), (0, 1, 1), (1, 1, 1), (1, 1, 0)],
    (0, -1, 0): [(0, 0, 0), (1, 0, 0), (1, 0, 1), (0, 0, 1)],
    (0, 0, 1): [(0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)],
    (0, 0, -1): [(0, 0, 0), (0, 1, 0), (1, 1, 0), (1, 0, 0)],
}
FACE_NORMALS = np.array(list(CUBE_FACES), np.float64)


def cube_geometry(corner: np.ndarray, size: float) -> Geometry:
    triangles = []
    for a, b, c, d in CUBE_FACES.values():
        triangles += [[a, b, c], [a, c, d]]
    positions = corner + size * np.array(triangles, np.float64)
    return make_geometry(positions, material_ids=np.repeat(np.arange(6), 2), object_ids=np.zeros(12))


def test_cube_faces_give_known_distances_normals_and_materials():
    tracer = Tracer(cube_geometry(np.zeros(3), 1.0))
    # From 2 units outside each face centre, straight at it; then from the centre, out through it.
    face_centres = 0.5 + 0.5 * FACE_NORMALS
    outside = tracer.intersect(*rays(face_centres + 2 * FACE_NORMALS, -FACE_NORMALS))
    np.testing.assert_allclose(outside.distance, 2.0, rtol=1e-6)
    np.testing.assert_allclose(outside.position, face_centres, atol=1e-6)
    np.testing.assert_allclose(outside.geometric_normal, FACE_NORMALS, atol=1e-6)
    assert outside.material_id.tolist() == list(range(6))
    inside = tracer.intersect(*rays(np.full((6, 3), 0.5), FACE_NORMALS))
    np.testing.assert_allclose(inside.distance, 0.5, rtol=1e-6)
    np.testing.assert_allclose(inside.geometric_normal, FACE_NORMALS, atol=1e-6)
    assert inside.material_id.tolist() == list(range(6))


def random_unit_vectors(rng, count):
    vectors = rng.normal(size=(count, 3))
    return vectors / np.linalg.norm(vectors, axis=-1, keepdims=True)


@pytest.mark.parametrize("corner", [(-0.5, -0.5, -0.5), (3000.0, -2000.0, 1000.0)])
def test_offset_origins_do_not_self_hit(corner):
    """Rays leaving a convex cube's surface: outward ones must miss, inward ones must reach
    another face. Far from the origin the offset must exceed float32 rounding of the coordinates."""
    rng = np.random.default_rng(7)
    corner = np.array(corner)
    tracer = Tracer(cube_geometry(corner, 1.0))
    num_points = 2000
    targets = corner + rng.uniform(0.02, 0.98, size=(num_points, 3))
    eyes = corner + 0.5 + 3 * random_unit_vectors(rng, num_points)
    surface = tracer.intersect(*rays(eyes, targets - eyes))
    assert surface.hit.all()
    normals = surface.geometric_normal
    # Random directions, flipped into the outer or the inner hemisphere.
    directions = random_unit_vectors(rng, num_points)
    outward = directions * np.sign(np.sum(directions * normals, axis=-1, keepdims=True))
    for direction, expect_hit in ((outward, False), (-outward, True)):
        direction = direction.astype(np.float32)
        origins = tracer.offset_origins(surface.position, normals, direction)
        leaving = tracer.intersect(origins, direction)
        assert (leaving.hit == expect_hit).all()
        if expect_hit:
            assert (leaving.material_id != surface.material_id).all()
        blocked = tracer.occluded(origins, direction, np.full(num_points, 10, np.float32))
        assert (blocked == expect_hit).all()


def test_epsilon_scales_with_the_scene():
    near = Tracer(cube_geometry(np.zeros(3), 1.0))
    big = Tracer(cube_geometry(np.zeros(3), 1000.0))
    far = Tracer(cube_geometry(np.full(3, 1e5), 1.0))
    assert near.epsilon == pytest.approx(1e-4 * np.sqrt(3))
    assert big.epsilon == pytest.approx(1000 * near.epsilon)
    # 32 float32 ulps of the largest coordinate (1e5 + 1) dominate the tiny diagonal.
    assert far.epsilon == 32 * np.spacing(np.float32(1e5 + 1))


def brute_force_closest_hits(corners, origins, directions):
    """Slow, obviously-correct twin: Moller-Trumbore of every ray against every triangle, float64.

    Returns:
        t (R, T) ray parameter of each ray-triangle hit (inf where none), u (R, T), v (R, T).
    """
    p0, p1, p2 = (corners[:, k].astype(np.float64) for k in range(3))
    edge1, edge2 = p1 - p0, p2 - p0
    d = directions.astype(np.float64)[:, None, :]
    o = origins.astype(np.float64)[:, None, :]
    pvec = np.cross(d, edge2[None])
    det = np.sum(edge1[None] * pvec, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_det = 1.0 / det
        tvec = o - p0[None]
        u = np.sum(tvec * pvec, axis=-1) * inv_det
        qvec = np.cross(tvec, edge1[None])
        v = np.sum(d * qvec, axis=-1) * inv_det
        t = np.sum(edge2[None] * qvec, axis=-1) * inv_det
    valid = (np.abs(det) > 1e-12) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0)
    return np.where(valid, t, np.inf), u, v


def test_random_batch_agrees_with_brute_force_moller_trumbore():
    rng = np.random.default_rng(42)
    num_triangles, num_rays = 256, 4096
    centres = rng.uniform(-1, 1, size=(num_triangles, 1, 3))
    corners = (centres + rng.uniform(-0.3, 0.3, size=(num_triangles, 3, 3))).astype(np.float32)
    tracer = Tracer(make_geometry(corners))
    origins = rng.uniform(-2, 2, size=(num_rays, 3)).astype(np.float32)
    directions = (rng.uniform(-1, 1, size=(num_rays, 3)) - origins).astype(np.float32)
    t_far = rng.uniform(0.2, 1.5, size=num_rays).astype(np.float32)

    t, u, v = brute_force_closest_hits(corners, origins, directions)
    closest = np.argmin(t, axis=-1)
    rows = np.arange(num_rays)
    t_closest = t[rows, closest]
    # Rays whose answer hinges on rounding: grazing an edge of some triangle, two hits at nearly
    # the same t, or (for occlusion) a hit at nearly t_far. They must stay rare.
    margin = np.minimum(np.minimum(u, v), 1 - u - v)
    grazing = np.any((np.abs(margin) < 1e-5) & (np.abs(t) < 10), axis=-1)
    second = np.partition(t, 1, axis=-1)[:, 1]
    with np.errstate(invalid="ignore"):  # inf - inf where a ray hits nothing
        tied = np.abs(second - t_closest) < 1e-5 * np.maximum(1, t_closest)
    clear = ~(grazing | tied)
    assert clear.mean() > 0.98

    hits = tracer.intersect(origins, directions)
    ref_hit = np.isfinite(t_closest)
    assert 0.3 < ref_hit.mean() < 0.95
    np.testing.assert_array_equal(hits.hit[clear], ref_hit[clear])
    both = clear & ref_hit
    np.testing.assert_array_equal(hits.triangle_id[both], closest[both])
    np.testing.assert_allclose(hits.distance[both], t_closest[both], rtol=1e-5)
    np.testing.assert_allclose(hits.barycentrics[both, 0], u[rows, closest][both], atol=1e-4)
    np.testing.assert_allclose(hits.barycentrics[both, 1], v[rows, closest][both], atol=1e-4)
    expected_position = origins + hits.distance[:, None] * directions
    np.testing.assert_allclose(hits.position[both], expected_position[both], atol=1e-5)

    near_t_far = np.any(np.abs(t - t_far[:, None]) < 1e-5, axis=-1)
    decided = clear & ~near_t_far
    blocked = tracer.occluded(origins, directions, t_far)
    np.testing.assert_array_equal(blocked[decided], np.any(t <= t_far[:, None], axis=-1)[decided])
    assert 0.1 < blocked.mean() < 0.9


def test_chunked_and_threaded_batches_match_one_call(monkeypatch):
    rng = np.random.default_rng(3)
    corners = rng.uniform(-1, 1, size=(64, 3, 3)).astype(np.float32)
    origins = rng.uniform(-2, 2, size=(1000, 3)).astype(np.float32)
    directions = -origins
    t_far = np.full(1000, 0.8, np.float32)
    whole = Tracer(make_geometry(corners), num_threads=1)
    expected_hits = whole.intersect(origins, directions)
    expected_blocked = whole.occluded(origins, directions, t_far)

    monkeypatch.setattr(embree, "CHUNK_RAYS", 97)
    monkeypatch.setattr(embree, "MIN_THREAD_CHUNK_RAYS", 50)
    chunked = Tracer(make_geometry(corners), num_threads=3)
    hits = chunked.intersect(origins, directions)
    for name in ("hit", "distance", "triangle_id", "barycentrics", "position", "shading_normal", "uv", "material_id"):
        np.testing.assert_array_equal(getattr(hits, name), getattr(expected_hits, name))
    np.testing.assert_array_equal(chunked.occluded(origins, directions, t_far), expected_blocked)


def _bvhs(tracers) -> int:
    """Distinct Embree scenes among `tracers`."""
    return len({id(tracer._scene) for tracer in tracers})


def test_every_image_size_of_a_shot_shares_one_bvh(tmp_path):
    """A shot bake's pilot, measurement window and path-traced reference keep the shot's soup and
    trace one BVH (two had been held at once: the per-shot-size caches kept one each); a new soup
    releases the old BVH."""
    shot = SCENES["cornell_box"].write(tmp_path / "shot")
    scene = load_scene(shot, width=64, height=48)
    camera = find_camera(scene, SCENES["cornell_box"].camera)
    pilot_scene, pilot = resized(scene, camera, 32, 24)
    window_scene, window = measurement_window(scene, camera, 32 * 24)
    assert window is not camera
    bake_direct(pilot_scene, pilot, tmp_path / "pilot", "pilot", supersampling=1, texture_samples=1)
    bake_direct(window_scene, window, tmp_path / "window", "window", supersampling=1, texture_samples=1)
    tracer = PathTracer(window_scene, ReferenceSettings(spp=1, max_bounces=1, num_workers=2)).tracer
    gc.collect()
    with warnings.catch_warnings():  # isinstance on torch's deprecated module attributes warns
        warnings.simplefilter("ignore", FutureWarning)
        live = [obj for obj in gc.get_objects() if isinstance(obj, Tracer) and obj.geometry is scene.geometry]
    assert _bvhs(live) == 1
    assert tracer.num_threads == 1 and shared_tracer(scene, 3).num_threads == 3
    assert tracer.tangents is shared_tracer(scene, 3).tangents

    held = weakref.ref(shared_tracer(scene)._scene)
    del live, tracer
    shared_tracer(load_scene(shot, width=64, height=48))  # another soup of the same shot
    gc.collect()
    assert held() is None
