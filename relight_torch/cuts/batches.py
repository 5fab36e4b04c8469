"""The merged visibility cuts of every covered sub-sample (`VisibilityBatch`), in batches of rows of
similar length, made once and kept (they depend on neither the lights nor the materials), with
each batch's entries sorted by node for the illumination cut's new nodes."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from relight_torch.cuts.cuts import Cuts
from relight_torch.cuts.merge import MergedCuts, merge
from relight_torch.cuts.tree import LightTree

MERGE_ROWS = 2048
"""Sub-samples whose visibility cuts are merged together (`CutsRelighter.visibility_batches`), and
whose every merged entry is evaluated together (a new illumination cut, a roughness edit's rows),
each chunk cut to its own longest row: bounds the temporaries (the column sums' scatter stays in
cache), whatever `CutsRelightSettings.rows_per_batch`."""


@dataclass(frozen=True)
class VisibilityBatch:
    """The lit clusters of the merged visibility cuts of a batch of sub-samples (no lights, no
    materials), one row per sub-sample, padded to the batch's largest row M.

    Attributes:
        rows: (P,) int64 the batch's sub-samples.
        geometry: (P, 3, 4) their shading frames (tangent, bitangent, normal) and the direction
            to the viewer in that frame taken back to world (frame @ wo_local), as columns: a
            world direction's row times it gives its local coordinates and E.L (made by `CutsRelighter`).
        node: (P, M) int32 each row's merged clusters' nodes, ascending, then padding (2L - 1:
            one past the last node).
        visibility: (P, M) barycentric blend of the three vertices' means (> 0; padding 0).
        length: (P,) int32 each row's clusters (the rest is padding): a roughness edit's rows are
            cut to their longest without a pass over their entries.
        inputs: entries of the batch's vertices' visibility cuts (the merge's input).
        dark: merged clusters dark at all three vertices (dropped).
    """

    rows: torch.Tensor
    geometry: torch.Tensor
    node: torch.Tensor
    visibility: torch.Tensor
    length: torch.Tensor
    inputs: int
    dark: int


class VisibilityBatches:
    """The kept `VisibilityBatch`es of a cache's sub-samples.

    Args:
        tree: the light tree over L leaves.
        visibility: the lattice vertices' visibility cuts.
        sample_vertices: (N, 3) int64 lattice vertices of each covered sub-sample.
        sample_weights: (N, 3) their barycentric weights.
        geometry: (N, 3, 4) each sub-sample's `VisibilityBatch.geometry`.
    """

    def __init__(
        self,
        tree: LightTree,
        visibility: Cuts,
        sample_vertices: torch.Tensor,
        sample_weights: torch.Tensor,
        geometry: torch.Tensor,
    ):
        self.tree = tree
        self.visibility = visibility
        self.sample_vertices = sample_vertices
        self.sample_weights = sample_weights
        self.geometry = geometry
        self._batches: tuple[int, list[VisibilityBatch]] | None = None
        self._by_node: list[tuple[torch.Tensor, torch.Tensor] | None] | None = None

    def batches(self, batch_rows: int) -> list[VisibilityBatch]:
        """The merged visibility cuts of every covered sub-sample, in batches of `batch_rows`:
        computed on first use, then kept. Sub-samples are batched in the order of their vertices'
        cut sizes, so that a batch's merged cuts have similar sizes."""
        if self._batches is None or self._batches[0] != batch_rows:
            num_samples = self.sample_vertices.shape[0]
            inputs = self.visibility.sizes()[self.sample_vertices].sum(dim=1)
            order = torch.argsort(inputs, stable=True)
            batches = []
            for start in range(0, num_samples, batch_rows):
                rows = order[start : start + batch_rows]
                row, node, visibility, dark = [], [], [], 0
                for first in range(0, rows.shape[0], MERGE_ROWS):  # the merge's temporaries stay small
                    part = rows[first : first + MERGE_ROWS]
                    merged = self.merged(part)
                    blend = self._blend(merged, self.sample_weights[part])
                    # Clusters all three vertices see as dark stay dark however the illumination
                    # cut would split them: they are dropped before the illumination cut is merged in.
                    lit = blend > 0
                    row.append(merged.row[lit] + first)
                    node.append(merged.node[lit])
                    visibility.append(blend[lit])
                    dark += int((~lit).sum())
                length, padded_node, padded_visibility = _padded_rows(
                    torch.cat(row),
                    (torch.cat(node), torch.cat(visibility)),
                    rows.shape[0],
                    (self.tree.num_nodes, 0.0),
                )
                batches.append(
                    VisibilityBatch(
                        rows,
                        self.geometry[rows],
                        padded_node.int(),
                        padded_visibility,
                        length.int(),
                        int(inputs[rows].sum()),
                        dark,
                    )
                )
            self._batches = (batch_rows, batches)
            self._by_node = [None] * len(batches)
        return self._batches[1]

    def entries_by_node(self, index: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Batch `index`'s entries by node: ((Q,) int32 the flat (P M) positions of its rows'
        clusters, padding left out, sorted by node, (2L + 2,) int32 offsets: node n's entries are
        [offsets[n], offsets[n + 1]), n < 2L - 1). Made on first use (a light edit that changes
        part of the illumination cut) and kept; a frame's batches, on several threads, each fill
        their own entry of the list `batches` makes."""
        assert self._batches is not None and self._by_node is not None  # made with the batches
        batch = self._batches[1][index]
        entry = self._by_node[index]
        if entry is None:
            node = batch.node.view(-1)
            counts = torch.bincount(node, minlength=self.tree.num_nodes + 1)
            offsets = torch.cat((counts.new_zeros(1), torch.cumsum(counts, 0)))
            # The padding (node 2L - 1, sorted last) is never looked up: not kept.
            order = torch.argsort(node, stable=True)[: int(offsets[self.tree.num_nodes])].int()
            entry = self._by_node[index] = (order, offsets.int())
        return entry

    def merged(self, rows: torch.Tensor) -> MergedCuts:
        """The merged visibility cuts of the three lattice vertices of sub-samples `rows` (P,)."""
        vertices = self.sample_vertices[rows]
        return merge(self.tree, [(self.visibility, vertices[:, j]) for j in range(3)])

    def tensors(self) -> list[torch.Tensor]:
        """The tensors kept: the batches' and their entries by node."""
        tensors = [
            t
            for batch in (self._batches or (0, []))[1]
            for t in (batch.rows, batch.geometry, batch.node, batch.visibility, batch.length)
        ]
        return tensors + [t for index in (self._by_node or []) if index is not None for t in index]

    def _blend(self, merged: MergedCuts, weights: torch.Tensor) -> torch.Tensor:
        """(Q,) barycentric blend of the three vertices' cluster means; `weights` (P, 3) per row."""
        values = self.visibility.values
        row, cover = merged.row, merged.cover
        return (
            weights[row, 0] * values[cover[0]] + weights[row, 1] * values[cover[1]] + weights[row, 2] * values[cover[2]]
        )


def _padded_rows(
    row: torch.Tensor, values: tuple[torch.Tensor, ...], num_rows: int, fills: tuple[float, ...]
) -> tuple[torch.Tensor, ...]:
    """((P,) int64 entries per row, then (P, M) arrays of per-row entries: `values` (Q,) each, in
    rows `row` (Q,) int64 ascending, each row's entries in order then its `fill`); M the longest
    row (at least 1)."""
    counts = torch.bincount(row, minlength=num_rows)
    width = max(int(counts.max()) if num_rows else 0, 1)
    slot = (
        row * width
        + torch.arange(row.shape[0], device=row.device)
        - (torch.cumsum(counts, 0) - counts).index_select(0, row)
    )
    return counts, *(
        torch.full((num_rows * width,), fill, dtype=value.dtype, device=value.device)
        .index_copy_(0, slot, value)
        .view(num_rows, width)
        for value, fill in zip(values, fills, strict=True)
    )
