"""The light tree of Cheslack-Postava et al. 2008: a complete binary tree over L = 2^k point lights in post-order.

Leaves are the point lights in tree order (the bake permutes them so that sibling subtrees hold
coherent lights). A node of height h (leaves: h = 0) covers 2^h consecutive leaves; numbered in
post-order, each subtree is a contiguous index range ending at its root, so with
leftleaf(n) = the post-order index of n's leftmost leaf:

    the strict descendants of n are exactly the indices in [leftleaf(n), n)      (paper, property 1)
    cut nodes, sorted by index, run left to right                                (property 3)

For the leaf m (0-based, left to right) the post-order index is 2 m - popcount(m); a node of
height h whose leftmost leaf is m has index leftleaf + 2^(h+1) - 2, its right child n - 1 and
its left child n - 2^h.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


def _popcount(values: torch.Tensor) -> torch.Tensor:
    count = torch.zeros_like(values)
    remaining = values.clone()
    while bool((remaining > 0).any()):
        count += remaining & 1
        remaining >>= 1
    return count


@dataclass(frozen=True)
class LightTree:
    """Index arithmetic of the complete binary tree over `num_leaves` lights (a power of two).

    Attributes:
        num_leaves: L.
        leftleaf: (2L - 1,) int64 post-order index of each node's leftmost leaf.
        height: (2L - 1,) int64 height of each node (0 for leaves); |C| = 2^height.
        leaf_nodes: (L,) int64 post-order index of each leaf (tree order).
        level_nodes: per height h, (L / 2^h,) int64 post-order indices of that level, left to right.
    """

    num_leaves: int
    leftleaf: torch.Tensor
    height: torch.Tensor
    leaf_nodes: torch.Tensor
    level_nodes: tuple[torch.Tensor, ...]

    @staticmethod
    def of(num_leaves: int, device: torch.device | str = "cpu") -> LightTree:
        """The tree over `num_leaves` (a power of two >= 2) lights.

        Raises:
            ValueError: `num_leaves` is not a power of two >= 2.
        """
        if num_leaves < 2 or num_leaves & (num_leaves - 1):
            raise ValueError(f"the light tree needs a power-of-two number of lights >= 2, got {num_leaves}")
        num_nodes = 2 * num_leaves - 1
        leftleaf = torch.empty(num_nodes, dtype=torch.int64)
        height = torch.empty(num_nodes, dtype=torch.int64)
        levels = []
        h = 0
        while (1 << h) <= num_leaves:
            first_leaf = torch.arange(0, num_leaves, 1 << h, dtype=torch.int64)
            first_leaf_node = 2 * first_leaf - _popcount(first_leaf)
            nodes = first_leaf_node + (1 << (h + 1)) - 2
            leftleaf[nodes] = first_leaf_node
            height[nodes] = h
            levels.append(nodes.to(device))
            h += 1
        return LightTree(num_leaves, leftleaf.to(device), height.to(device), levels[0], tuple(levels))

    @property
    def num_nodes(self) -> int:
        return 2 * self.num_leaves - 1

    @property
    def root(self) -> int:
        return self.num_nodes - 1

    @property
    def size(self) -> torch.Tensor:
        """(2L - 1,) int64 |C| of each node: the number of leaves it covers."""
        return torch.ones_like(self.height) << self.height

    def aggregate(self, leaf_values: torch.Tensor) -> torch.Tensor:
        """Sums over every node's leaves.

        Args:
            leaf_values: (L, ...) values per leaf, in tree order.

        Returns:
            (2L - 1, ...) per node (post-order), the sum of its leaves' values.
        """
        if leaf_values.shape[0] != self.num_leaves:
            raise ValueError(f"expected {self.num_leaves} leaf values, got {tuple(leaf_values.shape)}")
        sums = leaf_values.new_empty((self.num_nodes, *leaf_values.shape[1:]))
        level = leaf_values
        for nodes in self.level_nodes:
            if nodes.shape[0] != level.shape[0]:
                level = level.reshape(nodes.shape[0], 2, *level.shape[1:]).sum(dim=1)
            sums[nodes] = level
        return sums

    def aggregate_batch(self, leaf_values: torch.Tensor) -> torch.Tensor:
        """`aggregate` over a batch: (B, L) -> (B, 2L - 1) node sums."""
        return self.aggregate(leaf_values.T).T
