"""Tests of the tracing benchmark: its synthetic scene and camera, its table, and the command."""

import argparse

import numpy as np
import pytest

from pipeline import tracing_bench
from pipeline.commands import trace_bench
from pipeline.errors import RelightError
from pipeline.tracing import Tracer


def misalignment(geometry):
    """Largest 1 - cos(angle) between a triangle's mean corner normal and its facet normal."""
    corners = geometry.positions.astype(np.float64)
    face = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    face /= np.linalg.norm(face, axis=-1, keepdims=True)
    mean = geometry.normals.mean(axis=1)
    mean /= np.linalg.norm(mean, axis=-1, keepdims=True)
    return 1 - np.einsum("tk,tk->t", mean, face).min()


def test_heightfield_has_the_requested_size_and_consistent_normals():
    geometry = tracing_bench.heightfield_geometry(20_000)
    assert geometry.num_triangles == 2 * 100 * 100
    corners = geometry.positions.astype(np.float64)
    face_z = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])[:, 2]
    assert (face_z > 0).all()  # counter-clockwise seen from above
    np.testing.assert_allclose(np.linalg.norm(geometry.normals, axis=-1), 1, atol=1e-6)
    # Analytic normals: the facets converge to them, 1 - cos(angle) falling as the cell size squared.
    coarse = misalignment(tracing_bench.heightfield_geometry(5_000))
    assert misalignment(geometry) < 0.06
    assert 3 < coarse / misalignment(geometry) < 5
    np.testing.assert_allclose(geometry.uvs.reshape(-1, 2).min(axis=0), 0)
    np.testing.assert_allclose(geometry.uvs.reshape(-1, 2).max(axis=0), 1)
    assert np.bincount(geometry.material_ids).tolist() == [5000] * 4


def test_pinhole_rays_cover_the_field_of_view_top_row_first():
    eye, target = np.array([0.0, -3.0, 1.0]), np.array([0.0, 0.0, 1.0])
    origins, directions = tracing_bench.pinhole_rays(eye, target, 90.0, 3, 3)
    assert origins.shape == directions.shape == (9, 3)
    np.testing.assert_allclose(origins, np.broadcast_to(eye, (9, 3)))
    np.testing.assert_allclose(np.linalg.norm(directions, axis=-1), 1, atol=1e-6)
    np.testing.assert_allclose(directions[4], [0, 1, 0], atol=1e-7)
    # Pixel centres of the outer rows sit at 2/3 of the half-height tan(45 deg) = 1.
    np.testing.assert_allclose(directions[1], [0, 1, 2 / 3] / np.sqrt(1 + 4 / 9), atol=1e-6)
    np.testing.assert_allclose(directions[7], [0, 1, -2 / 3] / np.sqrt(1 + 4 / 9), atol=1e-6)
    np.testing.assert_allclose(directions[3], [-2 / 3, 1, 0] / np.sqrt(1 + 4 / 9), atol=1e-6)


def test_synthetic_camera_sees_mostly_terrain_and_shadow_rays_reach_the_light():
    geometry = tracing_bench.heightfield_geometry(2_000)
    origins, directions = tracing_bench.synthetic_rays(4_096)
    tracer = Tracer(geometry)
    assert 0.5 < tracer.intersect(origins, directions).hit.mean() < 0.95
    light = tracing_bench.light_position(geometry)
    shadow_origins, shadow_directions, t_far = tracing_bench.shadow_rays(tracer, origins, directions, light)
    # The origins sit epsilon off the surface and t_far stops epsilon short of the light.
    ends = shadow_origins + t_far[:, None] * shadow_directions
    assert np.linalg.norm(ends - light, axis=-1).max() < 2.01 * tracer.epsilon
    # Lit from behind, the waves facing away from the light (and a few behind them) are in shadow.
    assert 0.1 < tracer.occluded(shadow_origins, shadow_directions, t_far).mean() < 0.4


def test_benchmark_rows_compare_each_implementation_with_raw_embreex():
    geometry = tracing_bench.heightfield_geometry(2_000)
    origins, directions = tracing_bench.synthetic_rays(1_024)
    timings = tracing_bench.run_benchmark(geometry, origins, directions, repeats=1, num_threads=2)
    assert [(t.query, t.implementation) for t in timings] == [
        ("closest hit", "raw embreex"),
        ("closest hit", "Tracer, 1 thread"),
        ("closest hit", "Tracer + attributes, 1 thread"),
        ("closest hit", "Tracer, 2 threads"),
        ("closest hit", "Tracer + attributes, 2 threads"),
        ("occlusion", "raw embreex"),
        ("occlusion", "Tracer, 1 thread"),
        ("occlusion", "Tracer, 2 threads"),
    ]
    raw = {t.query: t for t in timings if t.implementation == "raw embreex"}
    for timing in timings:
        assert timing.median_seconds > 0
        assert timing.ratio == pytest.approx(raw[timing.query].median_seconds / timing.median_seconds)
        assert timing.rays_per_second == pytest.approx(timing.num_rays / timing.median_seconds)
    assert raw["closest hit"].num_rays == 1_024
    assert 0 < raw["occlusion"].num_rays < 1_024
    table = tracing_bench.format_table(timings).splitlines()
    assert len(table) == 2 + len(timings)
    assert table[2].split()[-1] == "1.00"


def run_command(argv):
    parser = argparse.ArgumentParser()
    trace_bench.add_parser(parser.add_subparsers())
    args = parser.parse_args(["trace-bench", *argv])
    return args.run(args)


def test_command_prints_the_table(capsys):
    assert run_command(["--triangles", "500", "--rays", "400", "--repeats", "1", "--threads", "2"]) == 0
    output = capsys.readouterr().out
    assert "512 triangles, 400 camera rays" in output
    assert "Tracer + attributes, 2 threads" in output


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--rays", "0"], "--rays must be at least 1"),
        (["--camera", "/Cam"], "--camera needs --scene"),
    ],
)
def test_command_rejects_bad_options(argv, message):
    with pytest.raises(RelightError, match=message):
        run_command(argv)
