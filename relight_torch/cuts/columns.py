"""What the cuts' beauty render keeps between frames (`FactorColumns`): the BRDF factor sums of every
sub-sample's merged cut per illumination-cut node, in column slots, and one frame's update of them
(`ColumnsFrame`): the columns of nodes new to the cut, the rows whose lobes changed, the products
with the nodes' light."""

from __future__ import annotations

import collections
from collections.abc import Callable
from dataclasses import dataclass

import torch

from relight_torch.cuts.batches import MERGE_ROWS, VisibilityBatch
from relight_torch.cuts.factors import FactorEvaluator
from relight_torch.cuts.node_table import Grid, NodeTable
from relight_torch.cuts.tree import LightTree

KEPT_GRID_SHARE = 0.5
"""A roughness edit keeps its rows' grid weights (`FactorColumns.grids`) for the next edit of the
same rows (a slider dragged) if they are at most this share of the sub-samples: (N / 2, K)
float32 at most, a quarter of the factor columns' bytes."""

PRODUCT_ROWS = 1024
"""Sub-samples whose factor columns are updated and multiplied with the light together: 4 MiB of
bfloat16 columns at a cut of 256, which stay in cache between the two."""


@dataclass
class FactorColumns:
    """What the beauty render keeps between frames (`CutsRelighter.cuts_image`).

    Per batch of `CutsRelighter.visibility_batches`, the BRDF factors (`preview_surface.split_factors`) of the
    merged cut summed per illumination-cut node, in K = max_cut column slots: a light edit that
    keeps a node keeps its column, a node new to the cut gets a free slot and only its column is
    computed; a material edit recomputes the lobes' factors (the third on) of the rows whose
    lobe changed (roughnesses).

    Attributes:
        key: (max_cut, factors F, dtype, rows per batch): a change starts afresh.
        slot_node: (K,) int64 the illumination-cut node in each slot, -1 if free.
        columns: per batch (P, F, K) factor sums (factor_dtype).
        counts: per batch (K,) int64 merged entries per slot.
        sums: (N, F, 3) float the factor sums times the light (diffuse light for the first two
            factors, specular for the others), summed over the cut.
        light_key: the illumination cut `sums` were made with.
        table: (K, 6) the slots' diffuse and specular light `sums` were made with (factor_dtype):
            a light edit that leaves it as it was (a dome moved: its directions are at infinity)
            makes no products.
        dirty: (N,) bool sub-samples whose columns are to be recomputed (material edits).
        grids: per batch, the last roughness edit's rows (D,) int64 and their chunks' `Grid`s
            (of the illumination cut `light_key`; at most `KEPT_GRID_SHARE` of the sub-samples),
            or None: an edit of the same rows shades them again without their bookkeeping.
    """

    key: tuple
    slot_node: torch.Tensor
    columns: list[torch.Tensor]
    counts: list[torch.Tensor]
    sums: torch.Tensor
    light_key: tuple | None
    table: torch.Tensor | None
    dirty: torch.Tensor
    grids: list[tuple[torch.Tensor, list[Grid]] | None]

    @classmethod
    def empty(
        cls,
        key: tuple,
        batches: list[VisibilityBatch],
        num_samples: int,
        dtype: torch.dtype,
        device: torch.device,
    ) -> FactorColumns:
        """Empty columns (every row dirty-free, no slot used) of `key`, with arrays for `batches`
        (none unless kept), their `sums` in `dtype` (the G-buffer's)."""
        max_cut, num_factors, factor_dtype, _ = key
        columns, counts = [], []
        for batch in batches:
            columns.append(torch.zeros((batch.rows.shape[0], num_factors, max_cut), dtype=factor_dtype, device=device))
            counts.append(torch.zeros(max_cut, dtype=torch.int64, device=device))
        return cls(
            key,
            torch.full((max_cut,), -1, dtype=torch.int64, device=device),
            columns,
            counts,
            torch.zeros((num_samples, num_factors, 3), dtype=dtype, device=device),
            None,
            None,
            torch.zeros(num_samples, dtype=torch.bool, device=device),
            [None] * len(columns),
        )

    def tensors(self) -> list[torch.Tensor]:
        """The tensors kept: the columns, their counts and sums, and the last roughness edit's grids."""
        tensors = [*self.columns, *self.counts, self.sums, self.dirty]
        for rows, grids in filter(None, self.grids):
            tensors += [rows, *(t for grid in grids for t in (grid.columns, grid.weight, grid.counts))]
        return tensors


@dataclass(frozen=True)
class ColumnsFrame:
    """One frame's update of `FactorColumns` (`ColumnsFrame.start`, then `batch` per batch).

    Attributes:
        state: the columns brought to the frame.
        keep: whether they are kept for the next frame (else each batch's are made and dropped).
        keep_grids: whether a roughness edit's grids are kept (`KEPT_GRID_SHARE`).
        slot: (K,) int64 the slot of each node of the illumination cut.
        new: (K,) bool whether the node is new to the slots.
        table: (slots, 6) the slots' diffuse and specular light (factor dtype).
        relit: whether `table` differs from the one the sums were made with.
        every_table: every node of the cut into its slot, when a new cut or dirty rows need it.
        new_table: the nodes to evaluate for new columns (`every_table` for a new cut), or None.
        factors: the factor sums of the frame's materials.
    """

    state: FactorColumns
    keep: bool
    keep_grids: bool
    slot: torch.Tensor
    new: torch.Tensor
    table: torch.Tensor
    relit: bool
    every_table: NodeTable | None
    new_table: NodeTable | None
    factors: FactorEvaluator

    @classmethod
    def start(
        cls,
        state: FactorColumns,
        keep: bool,
        light_key: tuple,
        cut: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
        tree: LightTree,
        node_size: torch.Tensor,
        factors: FactorEvaluator,
    ) -> ColumnsFrame:
        """The frame of the illumination cut `cut` (nodes (K,), diffuse and specular light (K, 3))
        keyed `light_key`; `node_size` (2L - 1,) float the nodes' leaf counts. Gives the cut's
        nodes their slots and `state` the cut's light."""
        nodes, diffuse_light, specular_light = cut
        factor_dtype = state.key[2]
        slot, new = assign_slots(state.slot_node, nodes, tree.num_nodes)
        table = torch.zeros((state.slot_node.shape[0], 6), dtype=state.sums.dtype, device=state.sums.device)
        table[slot] = torch.cat((diffuse_light, specular_light), dim=1)
        table = table.to(factor_dtype)
        relit = state.table is None or not torch.equal(state.table, table)
        if state.light_key != light_key:  # the kept grids are the last illumination cut's
            state.grids = [None] * len(state.grids)
        state.light_key, state.table = light_key, table
        # Tables of the nodes to evaluate: every node into its slot (a new cut, dirty rows), or
        # the nodes new to the cut in cut order.
        num_slots = state.slot_node.shape[0]
        every_table = (
            NodeTable.of(tree, nodes, torch.ones_like(new), node_size, slot, num_slots)
            if (bool(new.all()) or bool(state.dirty.any()))
            else None
        )
        new_table = (
            every_table if bool(new.all()) else (NodeTable.of(tree, nodes, new, node_size) if bool(new.any()) else None)
        )
        keep_grids = keep and int(state.dirty.sum()) <= KEPT_GRID_SHARE * state.dirty.shape[0]
        return cls(state, keep, keep_grids, slot, new, table, relit, every_table, new_table, factors)

    def batch(
        self,
        index: int,
        batch: VisibilityBatch,
        entries_by_node: Callable[[int], tuple[torch.Tensor, torch.Tensor]],
    ) -> collections.Counter[str]:
        """Batch `index`'s columns brought to this frame and its rows' sums; its `CutsRelighter.stats`.
        `entries_by_node`: `VisibilityBatches.entries_by_node`."""
        state, keep, slot, new, table = self.state, self.keep, self.slot, self.new, self.table
        new_table, every_table = self.new_table, self.every_table
        num_factors, factor_dtype = state.key[1], state.key[2]
        num_slots = state.slot_node.shape[0]
        device, dtype = state.sums.device, state.sums.dtype
        stats: collections.Counter[str] = collections.Counter()
        stats["inputs"] += batch.inputs
        stats["dark"] += batch.dark
        shape = (batch.rows.shape[0], num_factors, num_slots)
        columns = state.columns[index] if keep else torch.zeros(shape, dtype=factor_dtype, device=device)
        counts = state.counts[index] if keep else torch.zeros(shape[2], dtype=torch.int64, device=device)
        fresh = None  # (P, F, new nodes) float the columns of the nodes new to the cut, for their slots
        if new_table is not None and new_table.everything:
            counts.zero_()
            # Chunks of rows, each without the padding all its rows have (the column sums'
            # scatter stays in cache).
            for part in torch.arange(shape[0], device=device).split(MERGE_ROWS):
                values, grid = self.factors.columns(batch, new_table, num_factors, part)
                columns[int(part[0]) : int(part[-1]) + 1].copy_(values[:, :, :num_slots].transpose(0, 1))
                counts += grid.counts
            stats["evaluated"] += int(counts.sum())
        elif new_table is not None:
            values, grid = self.factors.columns(batch, new_table, num_factors, by_node=entries_by_node(index))
            fresh = values[:, :, : grid.counts.shape[0]].transpose(0, 1)
            counts[slot[new]] = grid.counts
            stats["evaluated"] += int(grid.counts.sum())
        dirty = state.dirty.index_select(0, batch.rows)
        dirty_rows = torch.nonzero(dirty).squeeze(1)
        if dirty_rows.shape[0] and not bool(new.all()):  # the lobes' factors (2 on) of their rows
            # The grids of the last edit if it was of the same rows (a roughness slider dragged).
            last = state.grids[index] if keep else None
            kept = last[1] if last is not None and torch.equal(last[0], dirty_rows) else None
            assert every_table is not None  # made whenever rows are dirty
            grids = []
            for number, part in enumerate(dirty_rows.split(MERGE_ROWS)):  # the column sums' scatter stays in cache
                values, grid = self.factors.columns(
                    batch,
                    every_table,
                    num_factors,
                    part,
                    first_factor=2,
                    grid=None if kept is None else kept[number],
                )
                grids.append(grid)
                stats["evaluated"] += int(grid.counts.sum())
                # The lobes' factors as one span of each row: ~25 % faster than a 3-D index_copy_.
                lobes = values[2:, :, :num_slots].transpose(0, 1).to(columns.dtype).contiguous()
                columns.view(shape[0], -1)[:, 2 * num_slots :].index_copy_(0, part, lobes.view(part.shape[0], -1))
            if keep:
                state.grids[index] = (dirty_rows, grids) if self.keep_grids else None
        stats["merged"] += int(counts[slot].sum())
        if self.relit or bool(new.any()):
            # Chunks of rows: the new slots written (scattered along the last axis: every
            # cache line of the columns is read and written) just before the products read them.
            for part in range(0, shape[0], PRODUCT_ROWS):
                chunk = columns[part : part + PRODUCT_ROWS]
                if fresh is not None:
                    chunk.index_copy_(2, slot[new], fresh[part : part + PRODUCT_ROWS].to(chunk.dtype))
                state.sums.index_copy_(0, batch.rows[part : part + PRODUCT_ROWS], light_sums(chunk, table, dtype))
        elif dirty_rows.shape[0]:
            state.sums.index_copy_(
                0,
                batch.rows.index_select(0, dirty_rows),
                light_sums(rows_of(columns, dirty_rows), table, dtype),
            )
        return stats


def assign_slots(slot_node: torch.Tensor, nodes: torch.Tensor, num_nodes: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Give every node of an illumination cut (K,) a column slot: its own if `slot_node` (S,)
    already holds it, else a slot no node of the cut holds. Updates `slot_node` in place.

    Returns:
        ((K,) int64 slot of each node, (K,) bool whether the node is new to the slots).
    """
    held = torch.nonzero(slot_node >= 0).squeeze(1)
    slot_of = torch.full((num_nodes,), -1, dtype=torch.int64, device=nodes.device)
    slot_of[slot_node.index_select(0, held)] = held
    slot = slot_of.index_select(0, nodes)
    new = slot < 0
    used = torch.zeros_like(slot_node, dtype=torch.bool)
    used[slot[~new]] = True
    slot[new] = torch.nonzero(~used).squeeze(1)[: int(new.sum())]
    slot_node.fill_(-1)
    slot_node[slot] = nodes
    return slot, new


def rows_of(columns: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """(R, F, K) the factor columns (P, F, K) of `rows` (R,) int64: one `index_select` of the
    flattened (P, F K) rows (on the CPU a bfloat16 `index_select` of the 3-D tensor ran ~20x
    slower: 28 against 1.5 ms for 10,000 of 16,384 rows at F K = 1,024)."""
    return columns.view(columns.shape[0], -1).index_select(0, rows).view(rows.shape[0], *columns.shape[1:])


def light_sums(columns: torch.Tensor, table: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """(P, F, 3) factor sums (P, F, K) times the slots' light (K, 6), as `dtype`: diffuse light
    (first three columns) for the first two factors, specular light for the others."""
    products = (columns.reshape(-1, columns.shape[2]) @ table).view(columns.shape[0], columns.shape[1], 6).to(dtype)
    return torch.cat((products[:, :2, :3], products[:, 2:, 3:]), dim=1)
