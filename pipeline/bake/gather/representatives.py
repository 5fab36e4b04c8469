"""View representatives: the view samples the indirect light is gathered at (the clustered-gather paper, 3.3.2).

The view samples are split into two sets sized by the ratio of diffuse to specular energy the
camera sees (`glossy_share`), each clustered with the paper's two-phase clustering in its 6-D
metric. To keep the clustering batched, the image is cut into square tiles and every tile's
samples are clustered at once into the same number of clusters (the set's share of its tile);
a representative is the member nearest its cluster's mean position. Every view sample then
gets the radial-basis weights of its nearest representatives of each set, found in the same
metric with a k-d tree.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from relight_torch.brdf.preview_surface import lobe_probabilities
from relight_torch.gather.clustering import cluster, features, nearest_members
from relight_torch.gather.reconstruction import rbf_weights
from relight_torch.gbuffer import GBuffer
from relight_torch.math.frame import to_local


@dataclass(frozen=True)
class Representatives:
    """One set of view representatives.

    Attributes:
        sample_index: (R,) int64 indices into the view samples.
        neighbours: (P, k) int64 indices into the R representatives, for each view sample.
        rbf: (P, k) float32 radial-basis weights, rows summing to 1.
    """

    sample_index: np.ndarray
    neighbours: np.ndarray
    rbf: np.ndarray


def view_features(view: GBuffer, position_weight: float) -> torch.Tensor:
    """(P, 6) clustering features of the view samples (shading normals)."""
    return features(view.position, view.normal, position_weight)


def glossy_share(view: GBuffer) -> float:
    """The specular lobes' share of the reflected energy the camera sees, in [0, 1]."""
    wo_local = to_local(view.wo_world(), view.tangent, view.bitangent, view.normal)
    return float(1.0 - lobe_probabilities(view.params, wo_local)[..., 0].mean()) if view.num_samples else 0.0


def _tiles(view: GBuffer, tile: int) -> tuple[np.ndarray, np.ndarray]:
    """(num_tiles, tile^2) sample index per tile slot (-1 where empty) and the tiles' ids."""
    _height, width = view.image_size
    row, col = np.divmod(view.pixel_index.numpy(), width)
    tiles_across = -(-width // tile)
    tile_id = (row // tile) * tiles_across + col // tile
    slot = (row % tile) * tile + col % tile
    used, compact = np.unique(tile_id, return_inverse=True)
    table = np.full((used.size, tile * tile), -1, np.int64)
    table[compact, slot] = np.arange(view.num_samples)
    return table, used


def choose_representatives(
    view: GBuffer, clusters_per_tile: int, tile: int, position_weight: float, tiles_per_batch: int = 256
) -> np.ndarray:
    """(R,) sorted indices of the view samples chosen as representatives.

    Args:
        view: the view samples (one per pixel centre).
        clusters_per_tile: clusters in each tile of tile x tile pixels (>= 1).
        position_weight: of the 6-D metric (`relight_torch.gather.clustering.features`).
        tiles_per_batch: tiles clustered together (bounds the (tiles, tile^2, K) distances).
    """
    table, _ = _tiles(view, tile)
    points = view_features(view, position_weight)
    chosen = []
    for start in range(0, table.shape[0], tiles_per_batch):
        block = torch.from_numpy(table[start : start + tiles_per_batch])
        valid = block >= 0
        safe = block.clamp(min=0)
        labels = cluster(points[safe], valid, clusters_per_tile)
        member = nearest_members(view.position[safe], valid, labels, clusters_per_tile)
        picked = torch.where(member >= 0, safe.gather(1, member.clamp(min=0)), -1)
        chosen.append(picked[member >= 0].numpy())
    return np.sort(np.concatenate(chosen)) if chosen else np.zeros(0, np.int64)


def reconstruction_weights(
    view: GBuffer, sample_index: np.ndarray, num_neighbours: int, position_weight: float
) -> Representatives:
    """Each view sample's nearest representatives in the 6-D metric and their RBF weights."""
    points = view_features(view, position_weight).numpy().astype(np.float64)
    num_kept = min(num_neighbours, sample_index.size)
    if num_kept == 0:  # no view sample (a camera that sees only sky): nothing to reconstruct
        return Representatives(
            sample_index, np.zeros((points.shape[0], 0), np.int64), np.zeros((points.shape[0], 0), np.float32)
        )
    distances, neighbours = cKDTree(points[sample_index]).query(points, k=num_kept)
    distances = np.asarray(distances, np.float64).reshape(points.shape[0], num_kept)
    neighbours = np.asarray(neighbours, np.int64).reshape(points.shape[0], num_kept)
    weights = rbf_weights(torch.from_numpy(distances)).numpy().astype(np.float32)
    return Representatives(sample_index, neighbours, weights)
