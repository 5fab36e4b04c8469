"""Top-down construction of Cheslack-Postava et al. 2008's light tree (section 3.4), as a leaf order.

Every node's lights are split in two equal halves: two cluster centres are chosen, the lights
sorted by d(s, c1) - d(s, c2) and cut in the middle; recursively, to single lights. The distance
is squared Euclidean over feature vectors, so one routine serves every metric of the paper:

    geometric (eq. 10)      features (K / d x, n): K^2 / d^2 |x - x_c|^2 + |n - n_c|^2
                            (environment lights: the direction is both, features = direction)
    data-driven (eq. 11-12) the geometric features scaled by sqrt(beta), beside the pilot
                            visibility vector scaled by sqrt((1 - beta) (K^2 + 1) A^2 / M)

Centres start at the light farthest from the node's mean and the light farthest from that one,
then alternate a few times with the means of the two sorted halves (balanced 2-means). All
nodes of a level are split at once (the tree is complete, so a level is a reshape).
"""

from __future__ import annotations

import numpy as np


def _squared_distance(features: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(G, m) squared distances of (G, m, D) features to (G, D) centres."""
    return np.square(features - centres[:, None, :]).sum(axis=-1)


def build_leaf_order(features: np.ndarray, iterations: int = 3) -> np.ndarray:
    """The light tree's leaf order.

    Args:
        features: (L, D) per light (L a power of two), the metric's feature vectors.
        iterations: centre updates per split.

    Returns:
        (L,) int64 permutation: leaf m of the tree is light order[m].
    """
    num_lights = features.shape[0]
    if num_lights < 2 or num_lights & (num_lights - 1):
        raise ValueError(f"the light tree needs a power-of-two number of lights >= 2, got {num_lights}")
    features = np.asarray(features, np.float32)
    order = np.arange(num_lights)
    groups = 1
    while groups < num_lights:
        size = num_lights // groups
        half = size // 2
        grouped = features[order].reshape(groups, size, -1)
        rows = np.arange(groups)
        mean = grouped.mean(axis=1)
        first = grouped[rows, np.argmax(_squared_distance(grouped, mean), axis=1)]
        second = grouped[rows, np.argmax(_squared_distance(grouped, first), axis=1)]
        for step in range(iterations + 1):
            difference = _squared_distance(grouped, first) - _squared_distance(grouped, second)
            ranks = np.argsort(difference, axis=1, kind="stable")
            if step < iterations:
                ordered = np.take_along_axis(grouped, ranks[..., None], axis=1)
                first, second = ordered[:, :half].mean(axis=1), ordered[:, half:].mean(axis=1)
        order = np.take_along_axis(order.reshape(groups, size), ranks, axis=1).reshape(-1)
        groups *= 2
    return order
