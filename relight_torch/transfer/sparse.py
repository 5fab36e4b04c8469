"""Wavelet rows kept sparse: the project's packed CSR-like layout, top-k culling and products.

Layout of R rows over D = n x n wavelet coefficients (`SparseRows`):

    values      (nnz, C) floating: the kept coefficients, RGB (C = 3) or one scalar (C = 1)
    indices     (nnz,) int32:      flat coefficient index i n + j, in [0, D)
    offsets     (R + 1,) int64:    row r holds entries offsets[r] : offsets[r + 1]
    row_colour  (R, 3) or None:    with scalar values, row r is values x row_colour[r]

The colour factorisation (`factor_colour`) stores a row as the best rank-1 product of a scalar
wavelet row and an RGB colour: exact where the row's colour does not vary over the gathers (a
diffuse receiver: its albedo; every row of M), an approximation for glossy receivers whose
specular lobe is not tinted like their diffuse one. It divides the values by 3 and turns the three
per-channel products into one `embedding_bag` over (D, 3) embeddings.

Invariants (checked by `SparseRows.check` and the tests): offsets[0] = 0, offsets[-1] = nnz,
offsets non-decreasing; within a row the indices are strictly increasing (sorted, unique).
`keep_top_k` also drops all-zero values. The product uses `torch.nn.functional.embedding_bag(mode="sum",
per_sample_weights=...)`: on this project's 2-core CPU it beat `torch.sparse_csr_tensor @` by ~2x
and a gather-multiply-sum by ~7x (shared/PERF_NOTES.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from relight_torch.transfer.haar import support_area


def entry_rows(offsets: torch.Tensor) -> torch.Tensor:
    """(nnz,) int64 row of each entry of a CSR layout with (R + 1,) offsets."""
    return torch.repeat_interleave(torch.arange(offsets.shape[0] - 1, device=offsets.device), offsets.diff().long())


@dataclass(frozen=True)
class SparseRows:
    """R sparse rows over `num_columns` wavelet coefficients (see the module doc).

    Attributes:
        values: (nnz, C) coefficient values.
        indices: (nnz,) int32 column of each value.
        offsets: (R + 1,) int64 row starts.
        num_columns: D, the number of wavelet coefficients (gathers) per row.
        row_colour: (R, 3) colour of each row when `values` are (nnz, 1) scalars, else None.
    """

    values: torch.Tensor
    indices: torch.Tensor
    offsets: torch.Tensor
    num_columns: int
    row_colour: torch.Tensor | None = None

    @property
    def num_rows(self) -> int:
        return int(self.offsets.shape[0]) - 1

    @property
    def num_bytes(self) -> int:
        """Bytes of the arrays as held."""
        arrays = (self.values, self.indices, self.offsets) + (() if self.row_colour is None else (self.row_colour,))
        return sum(t.numel() * t.element_size() for t in arrays)

    def to(self, device: torch.device | str, dtype: torch.dtype) -> SparseRows:
        """Move to `device`, values cast to `dtype` (indices and offsets keep theirs).

        The values keep their (nnz, C) shape but are stored channel by channel (strides (1, nnz)),
        so that each channel is a contiguous weight vector for `matmul`: with strided per-sample
        weights embedding_bag was 9x slower (1.9 s against 0.21 s for 307,200 x 100 x 3 on 2 cores).
        """
        planar = self.values.to(device, dtype).t().contiguous().t()
        colour = None if self.row_colour is None else self.row_colour.to(device, dtype)
        return SparseRows(planar, self.indices.to(device), self.offsets.to(device), self.num_columns, colour)

    def check(self) -> None:
        """Raise ValueError naming the first broken invariant of the layout."""
        nnz = self.indices.shape[0]
        if self.values.dim() != 2 or self.values.shape[0] != nnz or self.indices.dim() != 1:
            raise ValueError(
                f"values must be (nnz, C) and indices (nnz,); got {tuple(self.values.shape)} "
                f"and {tuple(self.indices.shape)}"
            )
        if self.indices.dtype != torch.int32 or self.offsets.dtype != torch.int64:
            raise ValueError(f"indices must be int32 and offsets int64; got {self.indices.dtype}, {self.offsets.dtype}")
        offsets = self.offsets
        if offsets.dim() != 1 or offsets.shape[0] < 1 or int(offsets[0]) != 0 or int(offsets[-1]) != nnz:
            raise ValueError(
                f"offsets must run from 0 to nnz = {nnz}; got {tuple(offsets.shape)} ending "
                f"{int(offsets[-1]) if offsets.numel() else None}"
            )
        if self.row_colour is not None and (self.values.shape[1] != 1 or self.row_colour.shape != (self.num_rows, 3)):
            raise ValueError(
                f"a row colour needs (nnz, 1) values and ({self.num_rows}, 3) colours; got "
                f"{tuple(self.values.shape)} and {tuple(self.row_colour.shape)}"
            )
        if self.row_colour is None and self.values.shape[1] != 3:
            raise ValueError(f"values without a row colour must be (nnz, 3); got {tuple(self.values.shape)}")
        if bool((offsets[1:] < offsets[:-1]).any()):
            raise ValueError("offsets must be non-decreasing")
        if nnz and (int(self.indices.min()) < 0 or int(self.indices.max()) >= self.num_columns):
            raise ValueError(f"indices must lie in [0, {self.num_columns})")
        row_of = entry_rows(offsets)
        same_row = row_of[1:] == row_of[:-1]
        if bool((same_row & (self.indices[1:] <= self.indices[:-1])).any()):
            raise ValueError("indices must be strictly increasing within each row")

    def select_rows(self, rows: torch.Tensor) -> SparseRows:
        """The rows `rows` ((K,) int64, any order) as K sparse rows, entries in their order, values
        kept planar (see `to`): the product of a few rows (`matmul`) without the others."""
        starts = self.offsets.index_select(0, rows)
        counts = self.offsets.index_select(0, rows + 1) - starts
        offsets = torch.zeros(rows.shape[0] + 1, dtype=self.offsets.dtype, device=self.offsets.device)
        torch.cumsum(counts, 0, out=offsets[1:])
        total = int(offsets[-1])
        entries = torch.repeat_interleave(starts - offsets[:-1], counts, output_size=total)
        entries += torch.arange(total, device=entries.device)
        values = self.values.t().index_select(1, entries).t()
        colour = None if self.row_colour is None else self.row_colour.index_select(0, rows)
        return SparseRows(values, self.indices.index_select(0, entries), offsets, self.num_columns, colour)

    def matmul(self, dense: torch.Tensor) -> torch.Tensor:
        """Rows times a dense wavelet vector, channel by channel.

        Args:
            dense: (D, 3) wavelet coefficients of the light.

        Returns:
            (R, 3): out[r, c] = sum_k values[k, c] dense[indices[k], c] over row r's entries, or with
            scalar values row_colour[r, c] sum_k values[k, 0] dense[indices[k], c].
        """
        if dense.shape != (self.num_columns, 3):
            raise ValueError(f"dense must be ({self.num_columns}, 3), got {tuple(dense.shape)}")
        indices = self.indices.long() if dense.device.type != "cpu" else self.indices
        offsets = self.offsets.to(indices.dtype)

        def bag(table: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
            result: torch.Tensor = _WeightedBag.apply(table.contiguous(), indices, offsets, weights.contiguous())
            return result

        if self.row_colour is not None:
            return bag(dense, self.values[:, 0]) * self.row_colour
        return torch.cat([bag(dense[:, c : c + 1], self.values[:, c]) for c in range(3)], dim=1)


def _weighted_bag(
    table: torch.Tensor, indices: torch.Tensor, offsets: torch.Tensor, weights: torch.Tensor
) -> torch.Tensor:
    """(R, C) out[r] = sum_k weights[k] table[indices[k]] over row r's entries (`SparseRows` layout)."""
    return torch.nn.functional.embedding_bag(
        indices, table, offsets, mode="sum", per_sample_weights=weights, include_last_offset=True
    )


class _WeightedBag(torch.autograd.Function):
    """`_weighted_bag`, differentiable in the table in reverse and in forward mode: torch's
    embedding_bag has no forward-mode derivative, which the light solver's Jacobians need
    (`relight_torch.solve.descent`). The product is linear in the table, so its forward derivative
    is the product of the table's tangent; the rows' weights are cache data and take no gradient."""

    @staticmethod
    def forward(ctx, table: torch.Tensor, indices: torch.Tensor, offsets: torch.Tensor, weights: torch.Tensor):
        if weights.requires_grad:
            raise ValueError("the sparse rows' values take no gradient")
        ctx.save_for_backward(indices, offsets, weights)
        ctx.save_for_forward(indices, offsets, weights)
        ctx.table_rows = table.shape[0]
        return _weighted_bag(table, indices, offsets, weights)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        indices, offsets, weights = ctx.saved_tensors
        rows = entry_rows(offsets)
        table_grad = grad.new_zeros((ctx.table_rows, grad.shape[1]))
        table_grad.index_add_(0, indices.long(), grad.index_select(0, rows) * weights.unsqueeze(1))
        return table_grad, None, None, None

    @staticmethod
    def jvp(ctx, table_tangent: torch.Tensor, *_: object) -> torch.Tensor:
        indices, offsets, weights = ctx.saved_tensors
        return _weighted_bag(table_tangent.contiguous(), indices, offsets, weights)


def keep_top_k(coefficients: torch.Tensor, num_kept: int) -> SparseRows:
    """Cull wavelet rows to their `num_kept` most important coefficients (Listing 9-5).

    Importance is the coefficient's magnitude (summed over channels) times the area of support
    of its basis function, so wide (smooth) basis functions win over narrow ones of the same
    magnitude. Kept values are stored unweighted; exact zeros are dropped, so a row may hold fewer.

    Args:
        coefficients: (R, n, n, C) Haar coefficients of R rows.
        num_kept: k >= 1.

    Returns:
        `SparseRows` with R rows over n^2 columns, values of the input dtype.
    """
    if coefficients.dim() != 4 or coefficients.shape[1] != coefficients.shape[2]:
        raise ValueError(f"coefficients must be (R, n, n, C), got {tuple(coefficients.shape)}")
    if num_kept < 1:
        raise ValueError(f"num_kept must be >= 1, got {num_kept}")
    num_rows, side, _, channels = coefficients.shape
    flat = coefficients.reshape(num_rows, side * side, channels)
    area = support_area(side, coefficients.device).reshape(-1).to(coefficients.dtype)
    importance = flat.abs().sum(-1) * area
    k = min(num_kept, side * side)
    kept = torch.topk(importance, k, dim=1, sorted=False).indices.sort(dim=1).values
    values = torch.gather(flat, 1, kept.unsqueeze(-1).expand(num_rows, k, channels))
    nonzero = (values != 0).any(dim=-1)
    offsets = torch.zeros(num_rows + 1, dtype=torch.int64, device=coefficients.device)
    offsets[1:] = nonzero.sum(dim=1).cumsum(0)
    return SparseRows(values[nonzero], kept[nonzero].to(torch.int32), offsets, side * side)


def factor_colour(coefficients: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Each row as a scalar row times a colour: the rank-1 least-squares fit (see the module doc).

    With A the row's (n^2, C) coefficients, the colour is the unit top eigenvector v of the C x C
    Gram matrix A^T A (sign chosen so its sum is positive) and the scalar row is A v; the kept
    energy is the top eigenvalue, so a row of one colour is reproduced exactly.

    Args:
        coefficients: (R, n, n, C) rows (Haar coefficients or gather values alike: the fit commutes
            with the orthonormal transform).

    Returns:
        (scalars (R, n, n, 1), colour (R, C) unit length), of the input dtype.
    """
    num_rows, side, _, channels = coefficients.shape
    flat = coefficients.reshape(num_rows, side * side, channels)
    gram = torch.einsum("rgc,rgd->rcd", flat.double(), flat.double())
    colour = torch.linalg.eigh(gram).eigenvectors[..., -1]
    colour = torch.where(colour.sum(-1, keepdim=True) < 0, -colour, colour).to(coefficients.dtype)
    scalars = torch.einsum("rgc,rc->rg", flat, colour)
    return scalars.reshape(num_rows, side, side, 1), colour


def cull(rows: SparseRows, num_kept: int) -> SparseRows:
    """Keep the `num_kept` most important entries of each row (`keep_top_k`'s order) of sparse rows.

    `cull(keep_top_k(x, k1), k2)` equals `keep_top_k(x, k2)` for k2 <= k1 (up to ties): a bake
    kept at k1 can be studied at any smaller k without evaluating its rows again.
    """
    if num_kept < 1:
        raise ValueError(f"num_kept must be >= 1, got {num_kept}")
    side = math.isqrt(rows.num_columns)
    area = support_area(side, rows.indices.device).reshape(-1).to(rows.values.dtype)
    importance = rows.values.abs().sum(-1) * area[rows.indices.long()]
    row_of = entry_rows(rows.offsets)
    # Most important first, then (stable) grouped by row: rank within the row is position - row start.
    by_importance = torch.argsort(importance, descending=True, stable=True)
    order = by_importance[torch.argsort(row_of[by_importance], stable=True)]
    rank = torch.arange(order.shape[0], device=order.device) - rows.offsets[row_of[order]]
    keep = torch.zeros_like(importance, dtype=torch.bool)
    keep[order] = rank < num_kept
    offsets = torch.zeros_like(rows.offsets)
    offsets[1:] = rows.offsets.diff().clamp(max=num_kept).cumsum(0)
    return SparseRows(rows.values[keep], rows.indices[keep], offsets, rows.num_columns, rows.row_colour)


def concatenate(parts: list[SparseRows]) -> SparseRows:
    """The rows of several `SparseRows` (same columns, all with or all without a row colour) in turn."""
    if not parts:
        raise ValueError("nothing to concatenate")
    starts = [0]
    for part in parts[:-1]:
        starts.append(starts[-1] + int(part.offsets[-1]))
    offsets = torch.cat([parts[0].offsets[:1]] + [p.offsets[1:] + s for p, s in zip(parts, starts, strict=True)])
    colours = [p.row_colour for p in parts if p.row_colour is not None]
    if colours and len(colours) != len(parts):
        raise ValueError("cannot concatenate rows with a row colour and rows without one")
    colour = torch.cat(colours) if colours else None
    return SparseRows(
        torch.cat([p.values for p in parts]),
        torch.cat([p.indices for p in parts]),
        offsets,
        parts[0].num_columns,
        colour,
    )


def column_norms(rows: SparseRows) -> torch.Tensor:
    """(D,) L2 norm of each column of the rows (over rows and channels, row colours applied).

    Column c is the image that wavelet light c (Haar basis function c of the gather light) casts
    on the view samples (the chapter's Figure 9-3); `cull_light` weighs lights by these norms.
    """
    row_of = entry_rows(rows.offsets)
    squares = rows.values.square().sum(-1)
    if rows.row_colour is not None:
        squares = squares * rows.row_colour.square().sum(-1)[row_of]
    norms = torch.zeros(rows.num_columns, device=squares.device, dtype=squares.dtype)
    return norms.index_add_(0, rows.indices.long(), squares).sqrt()


def cull_light(dense: torch.Tensor, norms: torch.Tensor, tolerance: float) -> torch.Tensor:
    """On-the-fly culling of weak wavelet lights (the chapter's section 9.8.3): `dense` (D, 3)
    with the coefficients of its weakest columns zeroed.

    A column's weight is |dense_c| ||F_c|| (`norms`, the chapter's per-block test); the weakest
    are dropped while their summed weight stays within `tolerance` (in [0, 1)) of the total, so
    that by the triangle inequality the product loses at most `tolerance` times that total in L2
    norm (over rows and channels). Zero-weight columns contribute nothing either way.
    """
    weight = dense.norm(dim=-1) * norms
    order = torch.argsort(weight)
    dropped = order[weight[order].cumsum(0) <= tolerance * weight.sum()]
    culled = dense.clone()
    culled[dropped] = 0.0
    return culled
