"""Cuts through the light tree as sorted sparse vectors, and how Cheslack-Postava et al. 2008 select them.

A cut is a set of tree nodes partitioning the leaves; it stores each node's post-order index
(ascending: left to right) and the mean of a function over the node's leaves. `Cuts` holds B cuts
in CSR form. Visibility cuts are refined from the root until every node k satisfies
|C_k| var(v_k) <= sigma^2 (the paper's eq. 5; the order of refinement does not change the final
cut, so the selection is one top-down pass); the illumination cut is refined by intensity, the
brightest splittable node first, up to a maximum size.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

import torch

from relight_torch.cuts.tree import LightTree

MEAN_LEVELS = 255
"""Environment mode: stored visibility means are round(<v> * MEAN_LEVELS) in uint8."""


def indirect_scale(num_leaves: int) -> float:
    """Indirect mode: the stored means are <V G> / `indirect_scale`, G in steradians: 2 pi / L,
    the share of a hemisphere of one of L surface points around a vertex enclosed by surfaces."""
    return 2.0 * math.pi / num_leaves


@dataclass(frozen=True)
class Cuts:
    """B cuts over one tree (CSR).

    Attributes:
        offsets: (B + 1,) int64; cut b is entries [offsets[b], offsets[b + 1]).
        nodes: (nnz,) int64 post-order node indices, ascending within each cut.
        values: (nnz, C) float cluster means.
    """

    offsets: torch.Tensor
    nodes: torch.Tensor
    values: torch.Tensor

    @property
    def num_cuts(self) -> int:
        return int(self.offsets.shape[0]) - 1

    def sizes(self) -> torch.Tensor:
        """(B,) int64 number of nodes of each cut."""
        return self.offsets[1:] - self.offsets[:-1]

    def check(self, tree: LightTree) -> None:
        """Raise ValueError unless every cut is sorted and partitions the leaves of `tree`."""
        sizes = self.sizes()
        if bool((sizes < 1).any()) or int(self.offsets[-1]) != self.nodes.shape[0]:
            raise ValueError("cut offsets do not describe non-empty cuts over the node array")
        if bool(((self.nodes < 0) | (self.nodes >= tree.num_nodes)).any()):
            raise ValueError(f"cut node indices outside [0, {tree.num_nodes})")
        leaves = tree.size[self.nodes]
        row = torch.repeat_interleave(torch.arange(self.num_cuts, device=sizes.device), sizes)
        covered = torch.zeros(self.num_cuts, dtype=torch.int64, device=sizes.device).index_add_(0, row, leaves)
        first = torch.zeros_like(self.nodes, dtype=torch.bool)
        first[self.offsets[:-1]] = True
        follows = first | (tree.leftleaf[self.nodes] > torch.roll(self.nodes, 1))
        if bool((covered != tree.num_leaves).any()) or not bool(follows.all()):
            raise ValueError("a cut is not a sorted partition of the tree's leaves")


def variance_cut_mask(tree: LightTree, variances: torch.Tensor, sigma: float) -> torch.Tensor:
    """Which nodes form each cut: refined from the root until |C_k| var_k <= sigma^2 (or a leaf).

    Args:
        variances: (B, 2L - 1) per-node variance of the function over the node's leaves.
        sigma: the error threshold (Cheslack-Postava et al. 2008: 1.5 to 3).

    Returns:
        (B, 2L - 1) bool: True on the cut's nodes.
    """
    fine = (tree.size.to(variances.dtype) * variances <= sigma * sigma) | (tree.height == 0)
    active = torch.zeros_like(fine)
    active[:, tree.root] = True
    for h in range(len(tree.level_nodes) - 1, 0, -1):
        parents = tree.level_nodes[h]
        split = active[:, parents] & ~fine[:, parents]
        active[:, parents - (1 << h)] = split  # left children (height h - 1)
        active[:, parents - 1] = split  # right children
    return active & fine


def cuts_from_mask(mask: torch.Tensor, node_values: torch.Tensor) -> Cuts:
    """`Cuts` of a (B, 2L - 1) node mask, with values (B, 2L - 1, C) at the chosen nodes."""
    rows, nodes = torch.nonzero(mask, as_tuple=True)
    counts = torch.bincount(rows, minlength=mask.shape[0])
    offsets = torch.cat((counts.new_zeros(1), counts.cumsum(0)))
    return Cuts(offsets, nodes, node_values[rows, nodes])


def intensity_cut(tree: LightTree, intensity: torch.Tensor, max_size: int) -> torch.Tensor:
    """The illumination cut: the root refined by highest node intensity up to `max_size` nodes.

    Args:
        intensity: (2L - 1,) non-negative intensity of each node (e.g. the summed luminance).
        max_size: the largest cut (Cheslack-Postava et al. 2008: 128 to 512); capped by the number of leaves.

    Returns:
        (K,) int64 node indices, ascending, K <= max_size.
    """
    if max_size < 1:
        raise ValueError(f"the illumination cut needs max_size >= 1, got {max_size}")
    priority = intensity.detach().cpu().double().tolist()
    height = tree.height.cpu().tolist()
    heap = [(-priority[tree.root], tree.root)]
    leaves: list[int] = []
    while heap and len(heap) + len(leaves) < max_size:
        _, node = heapq.heappop(heap)
        h = height[node]
        for child in (node - (1 << h), node - 1):
            if height[child] == 0:
                leaves.append(child)
            else:
                heapq.heappush(heap, (-priority[child], child))
    nodes = sorted(leaves + [node for _, node in heap])
    return torch.tensor(nodes, dtype=torch.int64, device=intensity.device)
