"""Truncated wavelet rows refitted to keep their response to probe lights.

Keeping a row's k largest Haar coefficients (`sparse.keep_top_k`) keeps its sum (the box
coefficient always survives: every other Haar function sums to zero), so a uniformly lit scene
loses nothing. Real gather light is far from uniform: a lamp lights a patch of the floor, the
light bounced between the walls gathers in the corners, and the fine structure of the rows (the
near-field peaks of receivers beside a wall, the gathers a block hides) correlates with it. On the
Cornell box the indirect light lost several per cent of its energy with 50 of 1,024 coefficients
per row (docs/TRANSFER.md has the measurement).

`refit_rows` therefore changes the kept coefficients of each row, and only those (the cache keeps
its size), by the least-norm correction that makes the truncated row reproduce the untruncated
row's products with Q probe lights exactly:

    min ||delta||^2  subject to  A (v + delta) = t,    delta = A^T (A A^T)^+ (t - A v)

per row and value channel, with A (Q, k) the probes' wavelet coefficients at the row's kept
indices, v its kept values and t its untruncated responses (Lawson & Hanson 1974, least squares
with linear equality constraints, here with the objective the identity). A light in the span of
the probes is then transferred exactly; any other light errs by the truncation's error on its
difference to that span. The bake's probes are the shot's own lights carried through the bounces,
then its largest objects lit uniformly (`pipeline.bake.transfer.probes`): edits start from the
lights, a colour edit of a shot light stays in their span, and a light that moves or narrows keeps
the largest objects' share of its transport.
"""

from __future__ import annotations

import torch

from relight_torch.transfer.sparse import SparseRows, entry_rows

ROWS_PER_SOLVE = 1024
"""Rows refitted together (bounds the (rows, Q, k) temporaries)."""
RCOND = 1e-6
"""Singular values of a row's probe matrix below this fraction of its largest are treated as zero
(probes that the kept coefficients cannot tell apart are fitted as one)."""


def dense_responses(coefficients: torch.Tensor, probes: torch.Tensor) -> torch.Tensor:
    """(R, Q, C) the products of untruncated wavelet rows with probe lights.

    Args:
        coefficients: (R, n, n, C) Haar coefficients of R rows.
        probes: (Q, n^2) Haar coefficients of Q scalar probe lights, flattened row-major.
    """
    num_rows, side, _, channels = coefficients.shape
    flat = coefficients.reshape(num_rows, side * side, channels)
    return torch.einsum("rdc,qd->rqc", flat, probes.to(flat.dtype))


def sparse_responses(rows: SparseRows, probes: torch.Tensor) -> torch.Tensor:
    """(R, Q, C) the products of sparse rows' values (row colours not applied) with probe lights
    (`probes` (Q, D) as in `dense_responses`)."""
    row_of = entry_rows(rows.offsets)
    at = probes.to(rows.values.dtype).t().index_select(0, rows.indices.long())  # (nnz, Q)
    products = at.unsqueeze(-1) * rows.values.unsqueeze(1)  # (nnz, Q, C)
    out = products.new_zeros(rows.num_rows, probes.shape[0], rows.values.shape[1])
    return out.index_add_(0, row_of, products)


def refit_rows(kept: SparseRows, probes: torch.Tensor, target: torch.Tensor) -> SparseRows:
    """`kept` with each row's values corrected so that its products with the probes equal `target`
    (the least-norm correction on the row's kept indices; see the module doc).

    Args:
        kept: R truncated rows (values (nnz, C)).
        probes: (Q, D) Haar coefficients of Q scalar probe lights; all-zero probes are ignored.
        target: (R, Q, C) the untruncated rows' products with them (`dense_responses`).

    Returns:
        `SparseRows` of the same layout and row colours, values of `kept`'s dtype.
    """
    if probes.dim() != 2 or probes.shape[1] != kept.num_columns:
        raise ValueError(f"probes must be (Q, {kept.num_columns}), got {tuple(probes.shape)}")
    if target.shape != (kept.num_rows, probes.shape[0], kept.values.shape[1]):
        raise ValueError(
            f"target must be ({kept.num_rows}, {probes.shape[0]}, {kept.values.shape[1]}), got {tuple(target.shape)}"
        )
    norms = probes.norm(dim=1)
    live = norms > 0
    if not bool(live.any()) or kept.indices.numel() == 0:
        return kept
    # Unit probes: the constraints are the same, the solve better conditioned.
    probes, target = (probes[live] / norms[live, None]).double(), (target[:, live] / norms[live, None]).double()
    values = kept.values.double()
    counts = kept.offsets.diff()
    width = int(counts.max())
    row_of = entry_rows(kept.offsets)
    slot = torch.arange(kept.indices.shape[0], device=counts.device) - kept.offsets[row_of]
    padded_index = torch.zeros(kept.num_rows, width, dtype=torch.long, device=counts.device)
    padded_value = values.new_zeros(kept.num_rows, width, values.shape[1])
    present = torch.zeros(kept.num_rows, width, dtype=torch.bool, device=counts.device)
    padded_index[row_of, slot] = kept.indices.long()
    padded_value[row_of, slot] = values
    present[row_of, slot] = True
    corrected = padded_value.clone()
    for start in range(0, kept.num_rows, ROWS_PER_SOLVE):
        rows = slice(start, start + ROWS_PER_SOLVE)
        # A: (rows, Q, k) the probes at each row's kept indices, zero in the padding.
        a = probes.t()[padded_index[rows]].transpose(1, 2) * present[rows].unsqueeze(1)
        residual = target[rows] - a @ padded_value[rows]  # (rows, Q, C)
        gram = a @ a.transpose(1, 2)
        delta = a.transpose(1, 2) @ (torch.linalg.pinv(gram, rtol=RCOND, hermitian=True) @ residual)
        corrected[rows] += delta
    return SparseRows(
        corrected[present].to(kept.values.dtype), kept.indices, kept.offsets, kept.num_columns, kept.row_colour
    )
