"""Shared surface points of the clustered gathers and the remembered shadow answers, against
loop-by-loop twins."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from pipeline.bake.gather.surface_points import NORMAL_BINS, merge_entries, share_points
from relight_torch.gather.remembered import RememberedVisibility
from relight_torch.lights.light import Light, LightKind, Shaping


def _slow_share(position, normal, albedo, object_id, cell_size):
    """Group gathers by (cell, normal bin, object) in a dict; groups in sorted key order."""
    groups: dict[tuple, list[int]] = {}
    for g in range(len(position)):
        cell = tuple(math.floor(float(x) / cell_size) for x in position[g])
        bins = tuple(min(max(math.floor((float(n) + 1.0) * NORMAL_BINS / 2), 0), NORMAL_BINS - 1) for n in normal[g])
        groups.setdefault(cell + bins + (int(object_id[g]),), []).append(g)
    index = np.zeros(len(position), np.int64)
    points = []
    for u, key in enumerate(sorted(groups)):
        members = groups[key]
        index[members] = u
        mean = position[members].astype(np.float64).mean(0)
        nearest = min(members, key=lambda g: (np.linalg.norm(position[g] - mean), g))
        n = normal[members].astype(np.float64).sum(0)
        points.append((position[nearest], n / np.linalg.norm(n), albedo[members].mean(0), object_id[nearest]))
    return points, index


@pytest.fixture
def gathers():
    """300 gathers on two walls meeting at a corner and a box face, some on a second object."""
    generator = np.random.default_rng(5)
    position = generator.uniform(0.0, 4.0, (300, 3)).astype(np.float32)
    normal = np.zeros((300, 3), np.float32)
    wall = generator.integers(0, 3, 300)
    position[wall == 0, 0] = 0.0
    normal[wall == 0] = (1.0, 0.0, 0.0)
    position[wall == 1, 1] = 0.0
    normal[wall == 1] = (0.0, 1.0, 0.0)
    normal[wall == 2] = (0.0, 0.0, -1.0)
    normal += generator.normal(0.0, 0.05, normal.shape).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    albedo = generator.uniform(0.1, 0.9, (300, 3)).astype(np.float32)
    object_id = (wall == 2).astype(np.int32) + (position[:, 2] > 3.0)
    return position, normal, albedo, object_id


def test_shared_points_match_their_loop_twin(gathers):
    points, index = share_points(*gathers, cell_size=1.0)
    expected, expected_index = _slow_share(*gathers, cell_size=1.0)
    np.testing.assert_array_equal(index, expected_index)
    assert points.position.shape == (len(expected), 3) and 50 < len(expected) < 300
    for name, column in (("position", 0), ("normal", 1), ("albedo", 2), ("object", 3)):
        np.testing.assert_allclose(getattr(points, name), np.array([e[column] for e in expected]), rtol=1e-5, atol=1e-6)
    # Every shared point is one of its gathers (a real surface point) on the same object.
    np.testing.assert_array_equal(points.object[index], gathers[3])
    assert np.isin(points.position.view(np.dtype((np.void, 12))), gathers[0].view(np.dtype((np.void, 12)))).all()


def test_cell_size_zero_shares_identical_points_only(gathers):
    position, normal, albedo, object_id = (np.concatenate((a, a[:40])) for a in gathers)
    points, index = share_points(position, normal, albedo, object_id, cell_size=0.0)
    assert points.position.shape[0] == 300
    np.testing.assert_array_equal(index[300:], index[:40])
    np.testing.assert_array_equal(points.position[index], position)


def test_merged_entries_sum_the_weights_of_a_representative_sharing_a_point():
    counts = np.array([4, 0, 3])
    index = np.array([2, 0, 2, 1, 5, 5, 5])
    weight = np.arange(21, dtype=np.float32).reshape(7, 3)
    offsets, columns, summed = merge_entries(counts, index, weight, num_points=6)
    np.testing.assert_array_equal(offsets, [0, 3, 3, 4])
    np.testing.assert_array_equal(columns, [0, 1, 2, 5])
    np.testing.assert_allclose(summed, [weight[1], weight[3], weight[0] + weight[2], weight[4:].sum(0)])


class _CountingVisibility:
    def __init__(self):
        self.calls = 0

    def occluder_distance(self, light, points, normals, directions, distances):
        self.calls += 1
        return directions[..., 0] + float(light.world_from_light[0, 3])


def test_remembered_visibility_answers_shaping_edits_from_memory():
    inner = _CountingVisibility()
    visibility = RememberedVisibility(inner)
    light = Light(path="/lamp", kind=LightKind.RECT, world_from_light=np.eye(4))
    points = torch.rand(5, 3)
    query = (points, torch.rand(5, 3), torch.rand(5, 2, 3), torch.rand(5, 2))
    first = visibility.occluder_distance(light, *query)
    shaped = dataclasses.replace(light, shaping=Shaping(focus=3.0, cone_angle=20.0), intensity=5.0)
    assert visibility.occluder_distance(shaped, *query) is first
    assert inner.calls == 1 and visibility.counters == {"queries": 1, "remembered": 1}
    other_points = (points + 1.0, *query[1:])
    visibility.occluder_distance(shaped, *other_points)  # other points: traced
    moved = np.eye(4)
    moved[0, 3] = 2.0
    torch.testing.assert_close(
        visibility.occluder_distance(dataclasses.replace(light, world_from_light=moved), *query), first + 2.0
    )
    assert inner.calls == 3
    visibility.forget("/lamp")
    visibility.occluder_distance(light, *query)
    assert inner.calls == 4
