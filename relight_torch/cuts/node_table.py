"""What the tree's nodes are to the wanted nodes of an illumination cut (`NodeTable`), and the grid
on which a batch's clusters spanning several of them are shaded (`Grid`): the bookkeeping of the
cut merge's BRDF factors (`cuts.factors`)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from relight_torch.cuts.merge import leaf_cut_index
from relight_torch.cuts.tree import LightTree

GRID_LIVE_SHARE = 0.75
"""A grid whose live columns (spanned by some row's cluster) are at most this share of its
columns is shaded on those alone, its factors then added into their columns (`grid_of`): ~2.3 ns
per live cell for four factors (one core) against ~5.4 per cell shaded, dead or not."""


@dataclass(frozen=True)
class NodeTable:
    """What each tree node is to the wanted nodes of an illumination cut (per frame), and the
    C output columns they are summed into.

    Attributes:
        nodes: (C,) int64 each column's illumination-cut node (2L - 1, the padding node, if none).
        size: (C,) float their leaf counts |C| (0 if none).
        column: (2L,) int64 per tree node (and the padding node 2L - 1 of `VisibilityBatch`):
            the column of the wanted node it lies in (< C), C if it lies in no wanted node (or is
            the padding), C + 1 if it spans several cut nodes, some of them wanted.
        start, end: (2L,) int64 the wanted nodes [start, end) a node overlaps, numbered in cut order.
        grid_source: (C,) int64 each column's wanted node in cut order (W: none); None if the
            columns are the wanted nodes in cut order.
        ranges: (2, R) int64 node ranges [first, end) holding every node of column != C: the
            wanted nodes' subtrees [leftleaf, node + 1) and the spanning nodes.
        inside_size: (2L,) float |C| of the nodes with column < C, else 0.
        num_wanted: W, the wanted nodes.
        everything: whether every node of the cut is wanted.
    """

    nodes: torch.Tensor
    size: torch.Tensor
    column: torch.Tensor
    start: torch.Tensor
    end: torch.Tensor
    grid_source: torch.Tensor | None
    ranges: torch.Tensor
    inside_size: torch.Tensor
    num_wanted: int
    everything: bool

    @staticmethod
    def of(
        tree: LightTree,
        nodes: torch.Tensor,
        wanted: torch.Tensor,
        node_size: torch.Tensor,
        columns: torch.Tensor | None = None,
        num_columns: int = 0,
    ) -> NodeTable:
        """The table of the cut `nodes` (K,) (sorted) whose `wanted` (K,) bool nodes are to be
        computed, into `num_columns` columns, `columns` (K,) int64 giving a wanted node's (e.g.
        its slot), or by default in cut order (C = W); `node_size` (2L - 1,) float |C| of
        every node. A node overlaps the cut nodes from the one holding its leftmost leaf to the
        one holding its rightmost (`leaf_cut_index`)."""
        cut_of = leaf_cut_index(tree, nodes)
        first = cut_of.index_select(0, tree.leftleaf)
        last = cut_of.index_select(0, torch.arange(tree.num_nodes, device=nodes.device) - tree.height)
        rank = torch.cumsum(wanted, 0)
        start = rank.index_select(0, first) - wanted.index_select(0, first).long()
        end = rank.index_select(0, last)
        wanted_index = torch.nonzero(wanted).squeeze(1)
        num_wanted = wanted_index.shape[0]
        grid_source = None
        if columns is None:
            columns, num_columns = rank - 1, num_wanted
        else:
            grid_source = torch.full((num_columns,), num_wanted, dtype=torch.int64, device=nodes.device).index_copy_(
                0, columns.index_select(0, wanted_index), torch.arange(num_wanted, device=nodes.device)
            )
        column_nodes = torch.full((num_columns,), tree.num_nodes, dtype=torch.int64, device=nodes.device).index_copy_(
            0, columns.index_select(0, wanted_index), nodes.index_select(0, wanted_index)
        )
        column = torch.where(
            first == last,
            torch.where(wanted.index_select(0, first), columns.index_select(0, first), num_columns),
            torch.where(end > start, num_columns + 1, num_columns),
        )
        pad = column.new_zeros(1)
        padded_size = torch.cat((node_size, node_size.new_zeros(1)))
        inside_size = torch.where(column < num_columns, node_size, 0.0)
        wanted_nodes = nodes.index_select(0, wanted_index)
        spanning = torch.nonzero(column == num_columns + 1).squeeze(1)
        ranges = torch.stack(
            (
                torch.cat((tree.leftleaf.index_select(0, wanted_nodes), spanning)),
                torch.cat((wanted_nodes, spanning)) + 1,
            )
        )
        return NodeTable(
            column_nodes,
            padded_size.index_select(0, column_nodes),
            torch.cat((column, pad + num_columns)),
            torch.cat((start, pad)),
            torch.cat((end, pad)),
            grid_source,
            ranges,
            torch.cat((inside_size, inside_size.new_zeros(1))),
            num_wanted,
            num_wanted == nodes.shape[0],
        )


@dataclass(frozen=True)
class Grid:
    """What a chunk of rows' factor sums (`FactorEvaluator.columns`) depend on besides the
    materials, past the entries' columns: a roughness edit keeps it for the next edit of the
    same rows (`FactorColumns.grids`).

    Attributes:
        columns: (G,) int64 the grid's columns, ascending: every column, or the live ones (some
            row's cluster spans their node; the others weigh 0 in every row) if at most
            `GRID_LIVE_SHARE` of them.
        weight: (P, G) float |C_j| <v> of the cluster spanning column j's node in each row (0: none).
        counts: (C,) int64 merged entries per column (grid cells and clusters inside the node).
    """

    columns: torch.Tensor
    weight: torch.Tensor
    counts: torch.Tensor


def grid_of(
    table: NodeTable,
    column: torch.Tensor,
    entry: torch.Tensor | None,
    flat_node: torch.Tensor,
    flat_visibility: torch.Tensor,
    num_rows: int,
    width: int,
) -> Grid:
    """The `Grid` of the (P, M) rows `flat_node`, `flat_visibility` (P M,) of a batch (M =
    `width`) whose entries `entry` (E,) int64 (None: all) have columns `column` (E,) int64
    (`NodeTable.column`)."""
    num_columns = table.nodes.shape[0]
    counts = torch.bincount(column, minlength=num_columns + 2)
    # Clusters spanning several illumination-cut nodes: a grid of the wanted nodes in cut order.
    spanning = torch.nonzero(column == num_columns + 1).squeeze(1)
    if entry is not None:
        spanning = entry.index_select(0, spanning)
    spanning_node = flat_node.index_select(0, spanning)
    num_wanted = table.num_wanted
    # int32 labels: the grid's zeros, running sums and gather move half the bytes of int64.
    label = torch.arange(1, spanning.shape[0] + 1, dtype=torch.int32, device=flat_node.device)
    base = torch.div(spanning, width, rounding_mode="floor") * (num_wanted + 1)
    start, end = table.start.index_select(0, spanning_node), table.end.index_select(0, spanning_node)
    steps = torch.zeros(num_rows * (num_wanted + 1), dtype=torch.int32, device=flat_node.device)
    steps.index_add_(0, base + start, label)
    steps.index_add_(0, base + end, -label)
    cluster = torch.cumsum(steps.view(num_rows, num_wanted + 1), dim=1, dtype=torch.int32)  # 0: none (last column: 0)
    # Grid cells holding a cluster, per wanted node in cut order (the last: none).
    covered = torch.cumsum(
        torch.bincount(start, minlength=num_wanted + 1) - torch.bincount(end, minlength=num_wanted + 1), 0
    )
    weight = (
        torch.cat((flat_visibility.new_zeros(1), flat_visibility.index_select(0, spanning)))
        .index_select(0, cluster.view(-1))
        .view(num_rows, num_wanted + 1)
    )
    source = table.grid_source
    covered = covered[:num_wanted] if source is None else covered.index_select(0, source)
    # The `dome` backdrop's chunks of 2,048 rows span ~147 of the cut's 256 nodes.
    live = torch.nonzero(covered).squeeze(1)
    if live.shape[0] > GRID_LIVE_SHARE * num_columns:  # every column
        live, size = torch.arange(num_columns, device=flat_node.device), table.size
        weight = weight[:, :num_wanted] if source is None else weight.index_select(1, source)
    else:
        size = table.size.index_select(0, live)
        weight = weight.index_select(1, live if source is None else source.index_select(0, live))
    return Grid(live, weight.mul_(size), covered + counts[:num_columns])
