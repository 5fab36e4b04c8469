"""The BRDF factors of a batch's merged cut (its visibility clusters merged with the illumination
cut) summed per wanted illumination-cut node (Cheslack-Postava et al. 2008's per-cluster BRDF,
`preview_surface.split_factors_cosines`), evaluated block by block (`cuts.blocks`)."""

from __future__ import annotations

import torch

from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.cuts.batches import VisibilityBatch
from relight_torch.cuts.blocks import BlockEvaluator, add_factors, slabs
from relight_torch.cuts.node_table import Grid, NodeTable, grid_of


class FactorEvaluator:
    """The factor sums of merged cuts for one frame's materials.

    Args:
        node_points: (3, 2L) per tree node its mean direction (env) or mean position (indirect) by
            component, and a last column for the padding node of `VisibilityBatch` (weight 0).
        cos_e: (N,) each sub-sample's cosine to the viewer in its stored frame.
        view_sq: (N,) the squared length of its local view direction (not quite 1: low-precision frames).
        position: (N, 3) the sub-samples' positions in indirect mode (directions towards the
            clusters' mean positions); None in env mode (the clusters' mean directions).
        params: the sub-samples' current material parameters.
        compiled: evaluate the blocks with `torch.compile`d code (`CutsRelightSettings.compiled`).
    """

    def __init__(
        self,
        node_points: torch.Tensor,
        cos_e: torch.Tensor,
        view_sq: torch.Tensor,
        position: torch.Tensor | None,
        params: PreviewSurfaceParams,
        compiled: bool,
    ):
        self.node_points = node_points
        self.cos_e = cos_e
        self.view_sq = view_sq
        self.position = position
        self.params = params
        self.compiled = compiled

    def columns(
        self,
        batch: VisibilityBatch,
        table: NodeTable,
        num_factors: int,
        rows: torch.Tensor | None = None,
        by_node: tuple[torch.Tensor, torch.Tensor] | None = None,
        first_factor: int = 0,
        grid: Grid | None = None,
    ) -> tuple[torch.Tensor, Grid]:
        """BRDF factors of a batch's merged cut (its visibility clusters merged with the
        illumination cut), summed per wanted illumination-cut node (`table`).

        A visibility cluster spanning several illumination-cut nodes is refined into them: each
        node j inside it is one entry, in j's direction, weighted |C_j| <v>. A row's clusters
        partition the leaves, so a row meets each node so at most once: these entries are shaded
        on a (P, W) grid, one column per wanted node, whose factors are the column sums; each
        cell's cluster is a running sum over the row of the clusters' ranges of wanted nodes
        (`node_table.grid_of`; only the columns some row's cluster spans if few are, `GRID_LIVE_SHARE`). A
        cluster inside one illumination-cut node is one entry in its own direction, summed into
        its column: shaded on the batch's (P, M) rows when every node is wanted (padding and
        spanning clusters weigh 0, a row's frame and material broadcast over its entries), else
        only the entries under or above wanted nodes are found (`by_node`) and shaded one by
        one. The BRDF runs on cache-sized blocks (`blocks.BlockEvaluator`: `preview_surface.split_factors_cosines`,
        eager or compiled, `CutsRelightSettings.compiled`).

        Args:
            table: the wanted nodes of the illumination cut and what each tree node is to them.
            rows: (P,) int64 rows of the batch to compute (default: all; every node wanted).
            by_node: the batch's `VisibilityBatches.entries_by_node` (needed unless every node is wanted).
            first_factor: factors before it are not summed, their sums unset (a lobe's width changes
                only the later ones).
            grid: the `Grid` of these rows and `table` if an earlier call made it.

        Returns:
            ((F, P, C + 2) float factor sums per column (`table`), then two zero columns; the
            rows' `Grid`, with the merged entries per column).
        """
        node, visibility = batch.node, batch.visibility
        samples, geometry = batch.rows, batch.geometry
        if rows is not None:  # their entries, less the padding all of them have
            width = max(int(batch.length.index_select(0, rows).max()), 1)
            node, visibility = node[:, :width].index_select(0, rows), visibility[:, :width].index_select(0, rows)
            samples, geometry = samples.index_select(0, rows), geometry.index_select(0, rows)
        (num_rows, width), num_columns = node.shape, table.nodes.shape[0]
        flat_node, flat_visibility = node.view(-1), visibility.view(-1)
        roughnesses = (self.params.roughness, self.params.clearcoat_roughness)[: num_factors // 2 - 1]
        roughnesses = tuple(r.index_select(0, samples).unsqueeze(1) for r in roughnesses)
        cos_e = self.cos_e.index_select(0, samples).unsqueeze(1)
        view_sq = self.view_sq.index_select(0, samples).unsqueeze(1)
        # Column of each entry: < C its wanted node's, C + 1 spanning several cut nodes (some
        # wanted), C none (or padding); the sums have two dump columns C, C + 1 of weight 0.
        if table.everything:
            entry = None  # every entry of the (P, M) rows
            column = table.column.index_select(0, flat_node)
        else:  # only the entries of the wanted nodes' subtrees and of the nodes above them
            assert by_node is not None  # callers pass it for a partial table
            order, offsets = by_node
            entry = order.index_select(
                0,
                _concatenated_ranges(
                    offsets.index_select(0, table.ranges[0]).long(), offsets.index_select(0, table.ranges[1]).long()
                ),
            ).long()
            column = table.column.index_select(0, flat_node.index_select(0, entry))
        if grid is None:
            grid = grid_of(table, column, entry, flat_node, flat_visibility, num_rows, width)
        sums = visibility.new_empty((num_factors, num_rows, num_columns + 2))
        blocks = BlockEvaluator(num_factors, visibility.dtype, visibility.device, self.compiled)
        self._grid_sums(blocks, table, grid, (geometry, samples, roughnesses, cos_e, view_sq), sums, first_factor)
        # Clusters inside one wanted illumination-cut node, summed into their columns: the
        # (P, M) rows as they are (padding and spanning clusters weigh 0), or one per line.
        if entry is None:
            lines = torch.arange(num_rows, device=node.device)
            column = column.view(num_rows, width)
        else:
            inside = torch.nonzero(column < num_columns).squeeze(1)
            entry = entry.index_select(0, inside)
            lines = torch.div(entry, width, rounding_mode="floor")
            node = flat_node.index_select(0, entry).view(-1, 1)
            visibility = flat_visibility.index_select(0, entry).view(-1, 1)
            column = column.index_select(0, inside).view(-1, 1)
        weight = table.inside_size.index_select(0, node.reshape(-1)).view(node.shape).mul_(visibility)
        cell = column.add_((lines * (num_columns + 2)).unsqueeze(1))
        flat = sums.view(-1)
        picked = None if entry is None else lines  # one entry per line: its row's values gathered per block
        for part in slabs(*node.shape):
            blocks.dense(
                self.node_points,
                node[part],
                _lines_of(geometry, part, picked),
                self._positions(_lines_of(samples, part, picked)),
                tuple(_lines_of(r, part, picked) for r in roughnesses),
                _lines_of(cos_e, part, picked),
                _lines_of(view_sq, part, picked),
                weight[part],
                cell[part].reshape(-1),
                flat,
                first_factor,
            )
        return sums, grid

    def _grid_sums(
        self, blocks: BlockEvaluator, table: NodeTable, grid: Grid, rows: tuple, sums: torch.Tensor, first_factor: int
    ) -> None:
        """The factors of a `Grid` of P rows written into the column sums `sums` (F, P, C + 2)
        (`columns`): every factor if the grid has every column, else the live columns'
        from `first_factor` on (the earlier factors unset); the rest 0. `rows`: (geometry,
        samples, roughnesses, cos_e, view_sq) of the P rows."""
        geometry, samples, roughnesses, cos_e, view_sq = rows
        num_factors, num_rows, _ = sums.shape
        num_columns, num_grid = table.nodes.shape[0], grid.columns.shape[0]
        in_place = num_grid == num_columns
        (sums[:, :, num_columns:] if in_place else sums[first_factor:]).zero_()
        nodes = table.nodes if in_place else table.nodes.index_select(0, grid.columns)
        parts = slabs(num_rows, num_grid)
        block = sums.new_empty(0 if in_place or not parts else num_factors * parts[0].stop * num_grid)
        for part in parts:
            size = part.stop - part.start
            out = (
                sums[:, part, :num_columns]
                if in_place
                else block[: num_factors * size * num_grid].view(num_factors, size, num_grid)
            )
            blocks.grid(
                self.node_points,
                nodes,
                geometry[part],
                self._positions(samples[part]),
                tuple(r[part] for r in roughnesses),
                cos_e[part],
                view_sq[part],
                grid.weight[part],
                out,
            )
            if not in_place:
                lines = torch.arange(part.start, part.stop, device=sums.device) * (num_columns + 2)
                add_factors(sums.view(-1), (grid.columns + lines.unsqueeze(1)).view(-1), out, first_factor)

    def _positions(self, rows: torch.Tensor) -> torch.Tensor | None:
        """(P, 3) positions of sub-samples `rows` (P,) in indirect mode; None in env mode."""
        return None if self.position is None else self.position.index_select(0, rows)


def _lines_of(values: torch.Tensor, part: slice, lines: torch.Tensor | None) -> torch.Tensor:
    """Per-row `values` (P, ...) for the lines `part` of a block: the rows themselves (`lines`
    None), or those of the lines' rows `lines` (E,) int64, gathered for this block only."""
    return values[part] if lines is None else values.index_select(0, lines[part])


def _concatenated_ranges(low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """(sum(high - low),) int64 the integers of the ranges [low, high) (R,), one after another."""
    counts = high - low
    owner = torch.repeat_interleave(torch.arange(low.shape[0], device=low.device), counts)
    return (low - (torch.cumsum(counts, 0) - counts)).index_select(0, owner) + torch.arange(
        owner.shape[0], device=low.device
    )
