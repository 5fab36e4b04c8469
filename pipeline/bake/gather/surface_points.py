"""Shared surface points of the clustered gathers: light each surface point once, index it many times.

The clustered gathers of neighbouring representatives land on the same surfaces, so lighting each
of them (the clustered-gather paper's D(g)) repeats nearly the same work hundreds of times. Here they are
snapped to a world grid: gathers in the same cell, normal bin (`NORMAL_BINS` per axis, so the two
sides of a thin wall or the walls meeting at a corner stay apart) and object (light links act per
object) share one surface point -- the member nearest their mean position, so that visibility is
still evaluated on a real surface point (as the paper places a cluster), with their mean normal
and albedo. A cell size of 0 shares only identical points (the unmerged method). A
representative's gathers that land on one shared point become one entry with their summed weight.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NORMAL_BINS = 4
"""Bins per normal component in [-1, 1]: normals in one bin differ by less than ~40 degrees."""


@dataclass(frozen=True)
class SurfacePoints:
    """U shared gather points.

    Attributes:
        position: (U, 3) float32 world position (one of the merged gathers).
        normal: (U, 3) float32 unit receiving normal (mean of the merged gathers').
        albedo: (U, 3) float32 diffuse albedo (mean of the merged gathers').
        object: (U,) int32 object id (index into `Scene.objects`).
    """

    position: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray
    object: np.ndarray


def _group_first(inverse: np.ndarray, order_key: np.ndarray, num_groups: int) -> np.ndarray:
    """(num_groups,) index of each group's member with the smallest `order_key` (ties: lowest index)."""
    order = np.lexsort((np.arange(inverse.size), order_key, inverse))
    starts = np.searchsorted(inverse[order], np.arange(num_groups))
    return order[starts]


def share_points(
    position: np.ndarray, normal: np.ndarray, albedo: np.ndarray, object_id: np.ndarray, cell_size: float
) -> tuple[SurfacePoints, np.ndarray]:
    """Merge G gathers into U shared surface points.

    Args:
        position, normal, albedo: (G, 3) the clustered gathers; object_id: (G,) their objects.
        cell_size: world size of a grid cell (> 0), or 0 to merge identical points only.

    Returns:
        (the shared points, (G,) int64 index of each gather's point).
    """
    if cell_size < 0:
        raise ValueError(f"cell_size must be >= 0, got {cell_size}")
    position = np.asarray(position, np.float32)
    if cell_size > 0:
        cells = np.floor(position / cell_size).astype(np.int64)
    else:
        cells = position.view(np.int32).astype(np.int64)
    bins = np.clip(np.floor((np.asarray(normal, np.float64) + 1.0) * (NORMAL_BINS / 2)), 0, NORMAL_BINS - 1)
    keys = np.column_stack((cells, bins.astype(np.int64), np.asarray(object_id, np.int64)))
    _, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    num_points = int(inverse.max()) + 1 if inverse.size else 0
    counts = np.bincount(inverse, minlength=num_points).astype(np.float64)[:, None]

    def group_sum(values: np.ndarray) -> np.ndarray:
        values = np.asarray(values, np.float64)
        return np.stack([np.bincount(inverse, values[:, c], num_points) for c in range(3)], axis=-1)

    mean_position = group_sum(position) / np.maximum(counts, 1.0)
    nearest = _group_first(inverse, np.linalg.norm(position - mean_position[inverse], axis=-1), num_points)
    normal_sum = group_sum(normal)
    unit_normal = normal_sum / np.maximum(np.linalg.norm(normal_sum, axis=-1, keepdims=True), 1e-12)
    points = SurfacePoints(
        position=position[nearest],
        normal=unit_normal.astype(np.float32),
        albedo=(group_sum(albedo) / np.maximum(counts, 1.0)).astype(np.float32),
        object=np.asarray(object_id, np.int32)[nearest],
    )
    return points, inverse.astype(np.int64)


def merge_entries(
    counts: np.ndarray, index: np.ndarray, weight: np.ndarray, num_points: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sum the weights of each representative's entries that share a point (CSR in, CSR out).

    Args:
        counts: (R,) entries of each representative (representative-major); index: (G,) their
            shared points in [0, num_points); weight: (G, 3).

    Returns:
        (offsets (R + 1,) int64, index (G',) int64 ascending within a representative, weight (G', 3)
        float32), G' <= G.
    """
    owner = np.repeat(np.arange(counts.size, dtype=np.int64), counts)
    keys, inverse = np.unique(owner * max(num_points, 1) + index, return_inverse=True)
    inverse = inverse.reshape(-1)
    weight = np.asarray(weight, np.float64)
    summed = np.stack([np.bincount(inverse, weight[:, c], keys.size) for c in range(3)], axis=-1)
    per_representative = np.bincount(keys // max(num_points, 1), minlength=counts.size)
    offsets = np.concatenate(([0], np.cumsum(per_representative))).astype(np.int64)
    return offsets, keys % max(num_points, 1), summed.astype(np.float32)
