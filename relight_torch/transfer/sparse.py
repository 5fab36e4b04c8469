"""Wavelet rows kept sparse: the project's packed CSR-like layout, top-k culling and products.

Layout of R rows over D = n x n wavelet coefficients (`SparseRows`):

    values   (nnz, C) floating: the kept coefficients (RGB, C = 3)
    indices  (nnz,) int32:      flat coefficient index i n + j, in [0, D)
    offsets  (R + 1,) int64:    row r holds entries offsets[r] : offsets[r + 1]

Invariants (checked by `SparseRows.check` and the tests): offsets[0] = 0, offsets[-1] = nnz,
offsets non-decreasing; within a row the indices are strictly increasing (sorted, unique).
`keep_top_k` also drops all-zero values. The product uses `torch.nn.functional.embedding_bag(mode="sum",
per_sample_weights=...)`: on this project's 2-core CPU it beat `torch.sparse_csr_tensor @` by ~2x
and a gather-multiply-sum by ~7x (shared/PERF_NOTES.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from relight_torch.transfer.haar import support_area


@dataclass(frozen=True)
class SparseRows:
    """R sparse rows over `num_columns` wavelet coefficients (see the module doc).

    Attributes:
        values: (nnz, C) coefficient values.
        indices: (nnz,) int32 column of each value.
        offsets: (R + 1,) int64 row starts.
        num_columns: D, the number of wavelet coefficients (gathers) per row.
    """

    values: torch.Tensor
    indices: torch.Tensor
    offsets: torch.Tensor
    num_columns: int

    @property
    def num_rows(self) -> int:
        return int(self.offsets.shape[0]) - 1

    @property
    def num_bytes(self) -> int:
        """Bytes of the three arrays as held."""
        return sum(t.numel() * t.element_size() for t in (self.values, self.indices, self.offsets))

    def to(self, device: torch.device | str, dtype: torch.dtype) -> "SparseRows":
        """Move to `device`, values cast to `dtype` (indices and offsets keep theirs).

        The values keep their (nnz, C) shape but are stored channel by channel (strides (1, nnz)),
        so that each channel is a contiguous weight vector for `matmul`: with strided per-sample
        weights embedding_bag was 9x slower (1.9 s against 0.21 s for 307,200 x 100 x 3 on 2 cores).
        """
        planar = self.values.to(device, dtype).t().contiguous().t()
        return SparseRows(planar, self.indices.to(device), self.offsets.to(device), self.num_columns)

    def check(self) -> None:
        """Raise ValueError naming the first broken invariant of the layout."""
        nnz = self.indices.shape[0]
        if self.values.dim() != 2 or self.values.shape[0] != nnz or self.indices.dim() != 1:
            raise ValueError(f"values must be (nnz, C) and indices (nnz,); got {tuple(self.values.shape)} "
                             f"and {tuple(self.indices.shape)}")
        if self.indices.dtype != torch.int32 or self.offsets.dtype != torch.int64:
            raise ValueError(f"indices must be int32 and offsets int64; got {self.indices.dtype}, {self.offsets.dtype}")
        offsets = self.offsets
        if offsets.dim() != 1 or offsets.shape[0] < 1 or int(offsets[0]) != 0 or int(offsets[-1]) != nnz:
            raise ValueError(f"offsets must run from 0 to nnz = {nnz}; got {tuple(offsets.shape)} ending "
                             f"{int(offsets[-1]) if offsets.numel() else None}")
        if bool((offsets[1:] < offsets[:-1]).any()):
            raise ValueError("offsets must be non-decreasing")
        if nnz and (int(self.indices.min()) < 0 or int(self.indices.max()) >= self.num_columns):
            raise ValueError(f"indices must lie in [0, {self.num_columns})")
        row_of = torch.repeat_interleave(torch.arange(self.num_rows, device=offsets.device), offsets.diff())
        same_row = row_of[1:] == row_of[:-1]
        if bool((same_row & (self.indices[1:] <= self.indices[:-1])).any()):
            raise ValueError("indices must be strictly increasing within each row")

    def matmul(self, dense: torch.Tensor) -> torch.Tensor:
        """Rows times a dense wavelet vector, channel by channel.

        Args:
            dense: (D, C) wavelet coefficients of the light (same C as `values`).

        Returns:
            (R, C): out[r, c] = sum_k values[k, c] dense[indices[k], c] over row r's entries.
        """
        if dense.shape != (self.num_columns, self.values.shape[1]):
            raise ValueError(f"dense must be ({self.num_columns}, {self.values.shape[1]}), got {tuple(dense.shape)}")
        indices = self.indices.long() if dense.device.type != "cpu" else self.indices
        offsets = self.offsets.to(indices.dtype)
        columns = [torch.nn.functional.embedding_bag(indices, dense[:, c:c + 1].contiguous(), offsets, mode="sum",
                                                     per_sample_weights=self.values[:, c].contiguous(),
                                                     include_last_offset=True)
                   for c in range(dense.shape[1])]
        return torch.cat(columns, dim=1)


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


def concatenate(parts: list[SparseRows]) -> SparseRows:
    """The rows of several `SparseRows` (same columns) one after the other."""
    if not parts:
        raise ValueError("nothing to concatenate")
    starts = [0]
    for part in parts[:-1]:
        starts.append(starts[-1] + int(part.offsets[-1]))
    offsets = torch.cat([parts[0].offsets[:1]] + [p.offsets[1:] + s for p, s in zip(parts, starts)])
    return SparseRows(torch.cat([p.values for p in parts]), torch.cat([p.indices for p in parts]), offsets,
                      parts[0].num_columns)
