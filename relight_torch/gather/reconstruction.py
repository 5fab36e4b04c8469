"""Radial-basis reconstruction of per-pixel values from the nearest view representatives.

The clustered-gather paper interpolates the indirect light of every view sample from its 10 closest
clustered view samples (equation 3's c_ik). The weights here are Gaussians of the feature-space
distance, their width set per pixel by its farthest kept neighbour, normalised to sum to one.
"""

from __future__ import annotations

import torch

NUM_NEIGHBOURS = 10
WIDTH_FRACTION = 0.5
"""Gaussian sigma as a fraction of the distance to the farthest kept neighbour."""


def rbf_weights(distances: torch.Tensor) -> torch.Tensor:
    """(P, k) weights summing to 1 per row from (P, k) distances to the k nearest representatives.

    Missing neighbours (infinite distance) get weight 0; a row whose neighbours are all at the
    same distance (or at 0) gets equal weights.
    """
    finite = torch.isfinite(distances)
    farthest = torch.where(finite, distances, 0.0).amax(dim=1, keepdim=True)
    sigma = (WIDTH_FRACTION * farthest).clamp(min=torch.finfo(distances.dtype).tiny)
    ratio = torch.where(finite, distances, 0.0) / sigma
    weights = torch.where(finite, torch.exp(-0.5 * ratio * ratio), 0.0)
    return weights / weights.sum(dim=1, keepdim=True).clamp(min=torch.finfo(distances.dtype).tiny)


def interpolate(values: torch.Tensor, neighbours: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """(P, C) sum over k of weights * values[neighbours].

    Args:
        values: (R, C) per-representative values; neighbours: (P, k) int64 indices into R
            (any index where the weight is 0); weights: (P, k).
    """
    if neighbours.shape[1] == 0:  # no representative (a camera that sees only sky): bags of nothing
        return values.new_zeros(neighbours.shape[0], values.shape[1])
    # A weighted embedding bag: ~7x faster on CPU than indexing (P, k, C) and summing over k.
    return torch.nn.functional.embedding_bag(
        neighbours.clamp(0, values.shape[0] - 1), values, per_sample_weights=weights.to(values.dtype), mode="sum"
    )
