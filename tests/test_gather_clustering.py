"""The batched two-phase clustering and RBF weights against slow, loop-by-loop twins."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from relight_torch.gather.clustering import cluster, hierarchical_seeds, kmeans, nearest_members
from relight_torch.gather.reconstruction import interpolate, rbf_weights
from relight_torch.gather.relighter import GatherSet


def _slow_seeds(points: np.ndarray, num_clusters: int, num_iterations: int) -> np.ndarray:
    """One set (M, D) of valid points: split the cluster of largest total distance, K - 1 times."""
    labels = np.zeros(len(points), np.int64)
    for new_label in range(1, num_clusters):
        totals = np.zeros(num_clusters)
        distance = np.zeros(len(points))
        for k in range(num_clusters):
            members = np.flatnonzero(labels == k)
            if members.size:
                distance[members] = np.linalg.norm(points[members] - points[members].mean(0), axis=1)
                totals[k] = distance[members].sum()
        target = int(np.argmax(totals))
        members = np.flatnonzero(labels == target)
        centre_a = points[members[np.argmax(distance[members])]]
        centre_b = 2.0 * points[members].mean(0) - centre_a
        side_b = np.zeros(len(members), bool)
        for _ in range(num_iterations):
            side_b = np.linalg.norm(points[members] - centre_b, axis=1) < np.linalg.norm(
                points[members] - centre_a, axis=1
            )
            if (~side_b).any():
                centre_a = points[members[~side_b]].mean(0)
            if side_b.any():
                centre_b = points[members[side_b]].mean(0)
        labels[members[side_b]] = new_label
    return labels


def _slow_kmeans(points: np.ndarray, labels: np.ndarray, num_clusters: int, num_iterations: int) -> np.ndarray:
    for _ in range(num_iterations):
        means = [points[labels == k].mean(0) if (labels == k).any() else None for k in range(num_clusters)]
        updated = np.array(
            [min((np.linalg.norm(p - m), k) for k, m in enumerate(means) if m is not None)[1] for p in points]
        )
        if (updated == labels).all():
            break
        labels = updated
    return labels


@pytest.fixture
def sets():
    """Three sets of 6-D points in blobs, each with a different number of valid points."""
    generator = np.random.default_rng(3)
    centres = generator.normal(size=(5, 6)) * 4.0
    points = centres[generator.integers(0, 5, size=(3, 60))] + generator.normal(size=(3, 60, 6))
    valid = np.ones((3, 60), bool)
    valid[1, 45:] = False
    valid[2, ::3] = False
    return torch.from_numpy(points), torch.from_numpy(valid)


def test_hierarchical_seeds_and_kmeans_match_their_loop_twins(sets):
    points, valid = sets
    seeds = hierarchical_seeds(points, valid, 7, num_split_iterations=3)
    refined = kmeans(points, valid, seeds, 7, num_iterations=6)
    for b in range(points.shape[0]):
        kept = valid[b].numpy()
        expected_seeds = _slow_seeds(points[b].numpy()[kept], 7, 3)
        np.testing.assert_array_equal(seeds[b].numpy()[kept], expected_seeds)
        np.testing.assert_array_equal(
            refined[b].numpy()[kept], _slow_kmeans(points[b].numpy()[kept], expected_seeds, 7, 6)
        )
        assert (seeds[b].numpy()[~kept] == -1).all() and (refined[b].numpy()[~kept] == -1).all()
        assert len(np.unique(expected_seeds)) == 7


def test_clustering_lowers_the_total_distance_below_a_random_partition(sets):
    points, valid = sets
    labels = cluster(points, valid, 5)
    random = torch.where(valid, torch.randint(0, 5, valid.shape, generator=torch.Generator().manual_seed(0)), -1)

    def cost(partition):
        total = 0.0
        for b in range(points.shape[0]):
            for k in range(5):
                members = points[b][(partition[b] == k) & valid[b]]
                if len(members):
                    total += float((members - members.mean(0)).norm(dim=1).sum())
        return total

    assert cost(labels) < 0.5 * cost(random)


def test_nearest_members_are_the_members_closest_to_their_mean(sets):
    points, valid = sets
    positions = points[..., :3]
    labels = cluster(points, valid, 6)
    members = nearest_members(positions, valid, labels, 6)
    for b in range(points.shape[0]):
        for k in range(6):
            inside = np.flatnonzero(((labels[b] == k) & valid[b]).numpy())
            if inside.size == 0:
                assert members[b, k] == -1
                continue
            mean = positions[b, inside].mean(0)
            expected = inside[np.argmin((positions[b, inside] - mean).norm(dim=1).numpy())]
            assert members[b, k] == expected


def test_a_set_with_fewer_distinct_points_than_clusters_leaves_clusters_empty():
    points = torch.tensor([[[0.0] * 6, [0.0] * 6, [1.0] * 6, [0.0] * 6]], dtype=torch.float64)
    labels = cluster(points, torch.ones(1, 4, dtype=torch.bool), 3)
    assert len(torch.unique(labels)) == 2
    assert labels[0, 0] == labels[0, 1] == labels[0, 3] != labels[0, 2]


def test_rbf_weights_sum_to_one_and_fall_with_distance():
    distances = torch.tensor(
        [[0.0, 1.0, 2.0, 4.0], [3.0, 3.0, 3.0, 3.0], [0.5, 1.0, torch.inf, torch.inf]], dtype=torch.float64
    )
    weights = rbf_weights(distances)
    torch.testing.assert_close(weights.sum(1), torch.ones(3, dtype=torch.float64))
    assert (weights[0, :-1] > weights[0, 1:]).all()
    torch.testing.assert_close(weights[1], torch.full((4,), 0.25, dtype=torch.float64))
    assert (weights[2, 2:] == 0).all()
    # sigma = half the farthest distance: exp(-0.5 (d / sigma)^2) for d = 0, 1, 2, 4 and sigma = 2.
    raw = torch.exp(-0.5 * (torch.tensor([0.0, 1.0, 2.0, 4.0], dtype=torch.float64) / 2.0) ** 2)
    torch.testing.assert_close(weights[0], raw / raw.sum())


def test_interpolation_reproduces_a_constant():
    values = torch.full((5, 3), 2.5)
    neighbours = torch.tensor([[0, 4, 2], [1, 1, 3]])
    weights = rbf_weights(torch.tensor([[0.1, 0.3, 0.2], [1.0, 2.0, 0.5]]))
    torch.testing.assert_close(interpolate(values, neighbours, weights), torch.full((2, 3), 2.5))


def _gather_set(offsets, neighbours, rbf, num_points=4) -> GatherSet:
    num_gathers = offsets[-1]
    generator = torch.Generator().manual_seed(1)
    return GatherSet(
        index=torch.randint(0, num_points, (num_gathers,), generator=generator),
        weight=torch.rand(num_gathers, 3, generator=generator),
        offsets=torch.tensor(offsets),
        neighbours=torch.tensor(neighbours),
        rbf=torch.tensor(rbf),
    )


def test_representative_values_are_equation_3s_inner_sums():
    gather_set = _gather_set([0, 2, 2, 5], [[0, 2], [2, 1]], [[0.5, 0.5], [1.0, 0.0]])
    radiance = torch.rand(4, 3, generator=torch.Generator().manual_seed(2))
    values = gather_set.representative_values(radiance)
    contributions = radiance[gather_set.index] * gather_set.weight
    expected = torch.stack([contributions[0:2].sum(0), torch.zeros(3), contributions[2:5].sum(0)])
    torch.testing.assert_close(values, expected)
    pixels = interpolate(values, gather_set.neighbours, gather_set.rbf)
    torch.testing.assert_close(pixels, torch.stack([0.5 * values[0] + 0.5 * values[2], values[2]]))
    # Grey weights take the one-bag path: the same sums.
    grey = dataclasses.replace(gather_set, weight=gather_set.weight[:, :1].expand(-1, 3).contiguous())
    contributions = radiance[grey.index] * grey.weight
    expected = torch.stack([contributions[0:2].sum(0), torch.zeros(3), contributions[2:5].sum(0)])
    torch.testing.assert_close(grey.representative_values(radiance), expected)
    assert grey._grey and not gather_set._grey
    # Weights grey up to float rounding (the diffuse set's) take it too; a real tint does not.
    rounded = dataclasses.replace(gather_set, weight=grey.weight * torch.tensor([1.0, 1.0 + 3e-7, 1.0 - 5e-7]))
    tinted = dataclasses.replace(gather_set, weight=grey.weight * torch.tensor([1.0, 1.0 + 1e-4, 1.0]))
    assert rounded._grey and not tinted._grey
    for weighted in (rounded, tinted):
        contributions = radiance[weighted.index] * weighted.weight
        expected = torch.stack([contributions[0:2].sum(0), torch.zeros(3), contributions[2:5].sum(0)])
        torch.testing.assert_close(weighted.representative_values(radiance), expected, rtol=2e-6, atol=0.0)


@pytest.mark.parametrize(
    "offsets, neighbours", [([1, 2, 5], [[0, 1]]), ([0, 3, 2, 5], [[0, 1]]), ([0, 2, 5], [[0, 2]])]
)
def test_gather_sets_reject_broken_layouts(offsets, neighbours):
    with pytest.raises(ValueError):
        _gather_set(offsets, neighbours, [[0.5, 0.5]])
