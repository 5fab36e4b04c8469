"""Two-phase clustering of sample sets (the clustered-gather paper's section 3.3.1), batched over sets.

Each of B sets holds M samples with features in R^D (the paper's 6-D metric: weighted position
and normal, `features`). Phase one seeds the clusters hierarchically: starting from one cluster,
the cluster with the largest total distance of its members to its mean is split in two by a
2-means, until there are K clusters. Phase two runs k-means from those clusters. Every step runs
on all B sets at once; sets have a validity mask (misses and padding are never clustered), and
a set with fewer distinct samples than K leaves some clusters empty (count 0).

Splitting a cluster: its first two centres are its member farthest from its mean and that
member's mirror image through the mean; then `num_split_iterations` 2-means steps. Ties go to
the lower cluster index (argmin / argmax), so the result is deterministic.
"""

from __future__ import annotations

import torch


def features(position: torch.Tensor, normal: torch.Tensor, position_weight: float) -> torch.Tensor:
    """(..., 6) clustering features [position_weight * position, normal].

    Args:
        position: (..., 3) world positions; normal: (..., 3) unit normals.
        position_weight: 1 / scene units; the paper's weighting makes opposite normals (distance 2)
            about as far apart as two points across the scene: 2 / scene diagonal.
    """
    return torch.cat((position * position_weight, normal), dim=-1)


def cluster_means(
    points: torch.Tensor, valid: torch.Tensor, labels: torch.Tensor, num_clusters: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-set cluster means.

    Args:
        points: (B, M, D) features; valid: (B, M) bool; labels: (B, M) int64 in [0, K) (any
            value where not valid).

    Returns:
        (means (B, K, D), zero for empty clusters; counts (B, K) members, in points' dtype).
    """
    weight = valid.to(points.dtype)
    index = labels.clamp(0, num_clusters - 1)
    sums = points.new_zeros(points.shape[0], num_clusters, points.shape[2])
    sums.scatter_add_(1, index.unsqueeze(-1).expand_as(points), points * weight.unsqueeze(-1))
    counts = points.new_zeros(points.shape[0], num_clusters).scatter_add_(1, index, weight)
    return sums / counts.clamp(min=1.0).unsqueeze(-1), counts


def _compact(mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The True columns of each row of a (B, M) mask, packed to the left.

    Returns:
        (index (B, W) int64 of the packed columns, M where a row has fewer than W; valid (B, W)),
        W the largest count in a row.
    """
    width = int(mask.sum(1).max()) if mask.numel() else 0
    slot = torch.where(mask, mask.cumsum(1) - 1, width)
    index = torch.full((mask.shape[0], width + 1), mask.shape[1], dtype=torch.int64, device=mask.device)
    index.scatter_(1, slot, torch.arange(mask.shape[1], device=mask.device).expand_as(mask))
    index = index[:, :width]
    return index, index < mask.shape[1]


def _masked_mean(points: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, D) mean of the (B, W, D) points where the (B, W) mask holds, and (B, 1) counts."""
    weight = mask.to(points.dtype).unsqueeze(1)
    count = weight.sum(-1)
    # A batched product: torch's CPU sum over a middle axis ran ~10x slower.
    return torch.bmm(weight, points).squeeze(1) / count.clamp(min=1.0), count


def hierarchical_seeds(
    points: torch.Tensor, valid: torch.Tensor, num_clusters: int, num_split_iterations: int = 4
) -> torch.Tensor:
    """Labels (B, M) int64 of K clusters made by repeatedly splitting the worst cluster in two.

    Each step works on the split cluster's members only, packed to the left (`_compact`), and
    updates the two clusters' total distances, so a step costs the size of the cluster it splits.

    Args:
        points: (B, M, D) features; valid: (B, M) bool.
        num_clusters: K >= 1.
        num_split_iterations: 2-means steps per split.

    Returns:
        (B, M) labels in [0, K), -1 where not valid.
    """
    if num_clusters < 1:
        raise ValueError(f"num_clusters must be >= 1, got {num_clusters}")
    num_sets, num_points = valid.shape
    labels = torch.where(valid, 0, -1)
    totals = points.new_zeros(num_sets, num_clusters)
    mean, _ = _masked_mean(points, valid)
    totals[:, 0] = torch.where(valid, (points - mean.unsqueeze(1)).norm(dim=-1), 0.0).sum(1)
    rows = torch.arange(num_sets, device=points.device)
    padded = torch.cat((points, points.new_zeros(num_sets, 1, points.shape[2])), dim=1)
    for new_label in range(1, num_clusters):
        target = totals.argmax(dim=1)
        index, members = _compact(valid & (labels == target.unsqueeze(1)))
        if index.shape[1] < 2:
            break  # every cluster left is a single point: no split changes anything
        cluster_points = padded.gather(1, index.unsqueeze(-1).expand(-1, -1, points.shape[2]))
        mean, _ = _masked_mean(cluster_points, members)
        distance = torch.where(members, (cluster_points - mean.unsqueeze(1)).norm(dim=-1), -1.0)
        centre_a = cluster_points[rows, distance.argmax(dim=1)]
        centre_b = 2.0 * mean - centre_a
        side_b = torch.zeros_like(members)
        for _ in range(num_split_iterations):
            side_b = members & (
                (cluster_points - centre_b.unsqueeze(1)).norm(dim=-1)
                < (cluster_points - centre_a.unsqueeze(1)).norm(dim=-1)
            )
            for side, centre in ((members & ~side_b, centre_a), (side_b, centre_b)):
                side_mean, count = _masked_mean(cluster_points, side)
                centre.copy_(torch.where(count > 0, side_mean, centre))
        for label, side, centre in ((target, members & ~side_b, centre_a), (new_label, side_b, centre_b)):
            distance = torch.where(side, (cluster_points - centre.unsqueeze(1)).norm(dim=-1), 0.0).sum(1)
            totals[rows, label] = distance
        extended = torch.cat((labels, labels.new_full((num_sets, 1), -1)), dim=1)
        extended.scatter_(1, index, torch.where(side_b, new_label, torch.where(members, target.unsqueeze(1), -1)))
        labels = extended[:, :num_points]
    return labels


def kmeans(
    points: torch.Tensor, valid: torch.Tensor, labels: torch.Tensor, num_clusters: int, num_iterations: int = 8
) -> torch.Tensor:
    """Refine labels (B, M) by k-means steps (assign to the nearest non-empty mean, recompute).

    Args:
        points: (B, M, D) features; valid: (B, M) bool; labels: (B, M) initial labels.
        num_clusters: K; num_iterations: the most assignment steps (stops early when stable).

    Returns:
        (B, M) labels in [0, K), -1 where not valid.
    """
    for _ in range(num_iterations):
        means, counts = cluster_means(points, valid, labels, num_clusters)
        distance = torch.cdist(points, means)
        distance = torch.where(counts.unsqueeze(1) > 0, distance, torch.inf)
        updated = torch.where(valid, distance.argmin(dim=-1), -1)
        if torch.equal(updated, labels):
            break
        labels = updated
    return labels


def cluster(
    points: torch.Tensor,
    valid: torch.Tensor,
    num_clusters: int,
    num_split_iterations: int = 4,
    num_kmeans_iterations: int = 8,
) -> torch.Tensor:
    """The two phases: `hierarchical_seeds` then `kmeans`. Returns (B, M) labels, -1 where not valid."""
    seeds = hierarchical_seeds(points, valid, num_clusters, num_split_iterations)
    return kmeans(points, valid, seeds, num_clusters, num_kmeans_iterations)


def nearest_members(
    positions: torch.Tensor, valid: torch.Tensor, labels: torch.Tensor, num_clusters: int
) -> torch.Tensor:
    """(B, K) index in [0, M) of each cluster's member nearest its mean position (3-D), or -1 if empty.

    The paper places a clustered sample at that member so that visibility is evaluated on a real
    surface point.
    """
    means, counts = cluster_means(positions, valid, labels, num_clusters)
    own = means.gather(1, labels.clamp(0, num_clusters - 1).unsqueeze(-1).expand_as(positions))
    distance = torch.where(valid, (positions - own).norm(dim=-1), torch.inf)
    best = positions.new_full((positions.shape[0], num_clusters), torch.inf)
    best.scatter_reduce_(1, labels.clamp(min=0), distance, reduce="amin")
    is_best = valid & (distance == best.gather(1, labels.clamp(min=0)))
    member = torch.arange(positions.shape[1], device=positions.device).expand_as(labels)
    index = torch.full_like(best, positions.shape[1], dtype=torch.int64)
    index.scatter_reduce_(1, labels.clamp(min=0), torch.where(is_best, member, positions.shape[1]), reduce="amin")
    return torch.where(counts > 0, index, -1)
