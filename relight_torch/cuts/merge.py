"""The cut merge of Cheslack-Postava et al. 2008 (section 3.2), batched over rows (pixels) with sorted sparse arrays.

The paper merges N cuts in one traversal: it repeatedly takes the smallest current index, and
where all current nodes overlap (max leftleaf <= min index) emits the deepest of them, the one
with the smallest index. The emitted nodes form the merged cut: the union of the cuts' nodes
less those with a strict descendant in the union. Batched, for every row at once:

    keys = row * (2L - 1) + node for every entry of the row's cuts; sort, drop duplicates
    keep a key iff its predecessor (in the same row) is below row * (2L - 1) + leftleaf(node):
         a strict descendant of `node` would lie in [leftleaf(node), node)
    cover_j = searchsorted(keys of cut j, merged key): the node of cut j at or above the merged
         node (cut j's first node at or after it in post-order)

A cut shared by every row (the frame's illumination cut) is merged in a second step, `refine`,
without copying it per row: a merged node the shared cut covers keeps one entry; a node above the
shared cut is replaced by the shared cut's nodes inside it, [leftleaf(node), node), a contiguous
slice of the sorted shared cut, found from the shared cut's index of the node's first and last
leaves. No per-row Python loop; cost grows with the merged cut size.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from relight_torch.cuts.cuts import Cuts
from relight_torch.cuts.tree import LightTree


@dataclass(frozen=True)
class MergedCuts:
    """The merged cuts of P rows, flattened.

    Attributes:
        row: (Q,) int64 row of each merged node, ascending.
        node: (Q,) int64 merged node (post-order), ascending within a row.
        cover: per source cut, (Q,) int64 index into that source's entries (`Cuts.nodes`) of
            the node covering the merged node.
    """

    row: torch.Tensor
    node: torch.Tensor
    cover: tuple[torch.Tensor, ...]


def _row_entries(cuts: Cuts, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(owner (E,), entry (E,)): the entries of cuts `rows` (P,), concatenated in row order."""
    start = cuts.offsets[rows]
    counts = cuts.offsets[rows + 1] - start
    owner = torch.repeat_interleave(torch.arange(rows.shape[0], device=rows.device), counts)
    first = torch.cumsum(counts, 0) - counts
    entry = start[owner] + torch.arange(owner.shape[0], device=rows.device) - first[owner]
    return owner, entry


def merge(tree: LightTree, sources: list[tuple[Cuts, torch.Tensor]]) -> MergedCuts:
    """Merge, for each of P rows, the cuts `cuts.rows[p]` of every source.

    Args:
        sources: (cuts, rows (P,) int64) per source: row p merges cut rows[p] of each.

    Returns:
        the merged cuts, `cover` in the order of `sources`.
    """
    num_nodes = tree.num_nodes
    keys, entries = [], []
    for cuts, rows in sources:
        owner, entry = _row_entries(cuts, rows)
        keys.append(owner * num_nodes + cuts.nodes[entry])
        entries.append(entry)
    merged = torch.unique(torch.cat(keys), sorted=True)
    row, node = merged // num_nodes, merged % num_nodes
    previous = torch.cat((merged.new_full((1,), -1), merged[:-1]))
    keep = previous < row * num_nodes + tree.leftleaf[node]
    merged, row, node = merged[keep], row[keep], node[keep]
    cover = tuple(entry[torch.searchsorted(key, merged)] for key, entry in zip(keys, entries, strict=True))
    return MergedCuts(row, node, cover)


def leaf_cut_index(tree: LightTree, shared: torch.Tensor) -> torch.Tensor:
    """(2L - 1,) int64: at each leaf's node index, the index into the cut `shared` (K,) (sorted,
    a partition of the leaves) of the cut node holding the leaf (0 at inner nodes). A node n
    overlaps the cut nodes from the one at leftleaf(n) to the one at n - height(n), its last leaf."""
    leaf_cut = torch.repeat_interleave(
        torch.arange(shared.shape[0], device=shared.device), tree.size.index_select(0, shared)
    )
    return torch.zeros(tree.num_nodes, dtype=torch.int64, device=shared.device).index_copy_(
        0, tree.leaf_nodes, leaf_cut
    )


def refine_nodes(
    tree: LightTree, node: torch.Tensor, shared: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Merge a cut shared by every row into merged nodes `node` (Q,) int64 (each row's a sorted partition).

    The shared cut's index of every leaf is tabulated once (`leaf_cut_index`); a node's leftmost
    leaf (leftleaf) and rightmost leaf (node - height) then name the first and last shared nodes
    it overlaps: one (a shared node covers it) or the run of shared nodes inside it.

    Args:
        shared: (K,) int64 sorted node indices of the shared cut (a partition of the leaves).

    Returns:
        (parent (R,), new_node (R,), shared_index (R,)), int64: the refined entries in order, each
        with the entry of `node` it refines, its node and its index into `shared`.
    """
    cut_of = leaf_cut_index(tree, shared)
    first = cut_of.index_select(0, tree.leftleaf.index_select(0, node))
    counts = cut_of.index_select(0, node - tree.height.index_select(0, node)) - first + 1
    if bool((counts == 1).all()):  # every node lies under a shared node: no expansion
        return torch.arange(node.shape[0], device=node.device), node, first
    parent = torch.repeat_interleave(counts)
    shared_index = (first - (torch.cumsum(counts, 0) - counts)).index_select(0, parent) + torch.arange(
        parent.shape[0], device=node.device
    )
    new_node = torch.where(
        (counts == 1).index_select(0, parent), node.index_select(0, parent), shared.index_select(0, shared_index)
    )
    return parent, new_node, shared_index


def refine(tree: LightTree, merged: MergedCuts, shared: torch.Tensor) -> MergedCuts:
    """Merge a cut shared by every row into `merged` (`refine_nodes`).

    Args:
        shared: (K,) int64 sorted node indices of the shared cut (a partition of the leaves).

    Returns:
        the merged cuts with the shared cut's index (into `shared`) appended to `cover`.
    """
    parent, node, shared_index = refine_nodes(tree, merged.node, shared)
    return MergedCuts(merged.row[parent], node, tuple(c[parent] for c in merged.cover) + (shared_index,))
