"""The cuts relighter's per-block BRDF evaluation: directions to the merged clusters, the
UsdPreviewSurface factors (`preview_surface.split_factors_cosines`) and their sums per
illumination-cut node, over blocks of about `SLAB_ENTRIES` entries.

Two ways to run the same Python functions (`BlockEvaluator`): eagerly, as in-place torch passes
over reused cache-sized buffers (about thirty passes per block), or compiled by `torch.compile`
(inductor, C++ on the CPU, dynamic shapes), which fuses the passes into a few loops per block
(`CutsRelightSettings.compiled`). The math is written once, here and in `preview_surface`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence

import torch

from relight_torch.brdf import preview_surface
from relight_torch.errors import RelightError

SLAB_ENTRIES = 1 << 17
"""Entries per block of the BRDF factor kernel: its eleven to thirteen (block,) float32 buffers stay in cache."""


def slabs(num_rows: int, width: int) -> list[slice]:
    """Row ranges of about `SLAB_ENTRIES` entries of a (num_rows, width) grid."""
    step = max(1, SLAB_ENTRIES // max(width, 1))
    return [slice(start, min(start + step, num_rows)) for start in range(0, num_rows, step)]


def work_blocks(
    flat: torch.Tensor, num_factors: int, rows: int, width: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """((F, rows, width) output, (4, rows, width) scratch, (3, rows, width) dot products): views
    of `flat` (at least (F + 7) rows width elements)."""
    blocks = flat[: (num_factors + 7) * rows * width].view(-1, rows, width)
    return blocks[:num_factors], blocks[num_factors : num_factors + 4], blocks[-3:]


def grid_dots(
    node_points: torch.Tensor, nodes: torch.Tensor, geometry: torch.Tensor, position: torch.Tensor | None
) -> torch.Tensor:
    """(P, 4, C) local coordinates (x, y, N.L) and E.L of the unit world directions towards the
    clusters `nodes` (C,) from P sub-samples of `geometry` (P, 3, 4) (`VisibilityBatch.geometry`).

    `node_points` (3, 2L) per node its mean direction (env: `position` None; one matrix product)
    or mean position (indirect: `position` (P, 3) the sub-samples' positions)."""
    if position is None:
        world = node_points.index_select(1, nodes)
        return (geometry.transpose(1, 2).reshape(-1, 3) @ world).view(geometry.shape[0], 4, nodes.shape[0])
    offset = node_points.index_select(1, nodes).t().unsqueeze(0) - position.unsqueeze(1)
    return torch.bmm(geometry.transpose(1, 2), torch.nn.functional.normalize(offset, dim=-1).transpose(1, 2))


def dense_dots(
    node_points: torch.Tensor,
    node: torch.Tensor,
    geometry: torch.Tensor,
    position: torch.Tensor | None,
    out: torch.Tensor,
    scratch: torch.Tensor,
) -> None:
    """N.L, E.L and |L|^2 (local coordinates: `grid_dots`) of the unit world directions towards
    merged clusters `node` (P, M) from P sub-samples of `geometry` (P, 3, 4), into `out` (3, P,
    M); `scratch` (4, P, M) overwritten. Componentwise multiply-adds: on the CPU a batched
    (M, 3) x (3, 4) product per row costs several times as much."""
    index = node.reshape(-1)
    for axis in range(3):
        torch.index_select(node_points[axis], 0, index, out=scratch[axis].view(-1))
    if position is not None:  # towards the clusters' mean positions
        for axis in range(3):
            scratch[axis].sub_(position[:, axis : axis + 1])
        torch.mul(scratch[0], scratch[0], out=scratch[3])
        scratch[3].addcmul_(scratch[1], scratch[1]).addcmul_(scratch[2], scratch[2]).clamp_min_(1e-24).rsqrt_()
        for axis in range(3):
            scratch[axis].mul_(scratch[3])
    targets = (scratch[3], scratch[3], out[0], out[1])  # x, y (only squared), N.L, E.L
    for column, target in enumerate(targets):
        torch.mul(scratch[0], geometry[:, 0, column : column + 1], out=target)
        target.addcmul_(scratch[1], geometry[:, 1, column : column + 1]).addcmul_(
            scratch[2], geometry[:, 2, column : column + 1]
        )
        if column == 0:
            torch.mul(target, target, out=out[2])
        elif column < 3:
            out[2].addcmul_(target, target)


def grid_block(
    node_points: torch.Tensor,
    nodes: torch.Tensor,
    geometry: torch.Tensor,
    position: torch.Tensor | None,
    roughnesses: tuple[torch.Tensor, ...],
    cos_e: torch.Tensor,
    view_sq: torch.Tensor,
    weight: torch.Tensor,
    out: torch.Tensor | Sequence[torch.Tensor],
    work: tuple,
) -> None:
    """The factors (F, P, C) of P sub-samples towards every cluster `nodes` (C,) into `out`
    (e.g. a view of the column sums); `weight` (P, C) |C| <v>, `roughnesses` (P, 1) each,
    `cos_e`, `view_sq` (P, 1) N.E and |E|^2; `work` (`work_blocks`, P x C; or tuples of (P, C)
    tensors, as `_fresh_work`) overwritten."""
    _, scratch, dots = work
    local = grid_dots(node_points, nodes, geometry, position)
    torch.mul(local[:, 0], local[:, 0], out=dots[2])
    dots[2].addcmul_(local[:, 1], local[:, 1]).addcmul_(local[:, 2], local[:, 2])
    preview_surface.split_factors_cosines(
        roughnesses, cos_e, local[:, 2], local[:, 3], weight, out, scratch, view_sq, dots[2]
    )


def dense_block(
    node_points: torch.Tensor,
    node: torch.Tensor,
    geometry: torch.Tensor,
    position: torch.Tensor | None,
    roughnesses: tuple[torch.Tensor, ...],
    cos_e: torch.Tensor,
    view_sq: torch.Tensor,
    weight: torch.Tensor,
    cells: torch.Tensor,
    sums: torch.Tensor,
    first_factor: int,
    work: tuple,
) -> None:
    """The factors of P sub-samples' entries `node` (P, M) (weight (P, M) |C| <v>, as
    `grid_block`) added into `sums` (F S,) (flat (F, S) sums) at the cells `cells` (P M,) int64
    of each factor's S; factors before `first_factor` are not added. `work` (`work_blocks`, P x
    M) overwritten. (The sums are one flat tensor, added to directly when compiled: an addition
    into a view of it would copy all of it.)"""
    out, scratch, dots = work
    dense_dots(node_points, node, geometry, position, dots, scratch)
    preview_surface.split_factors_cosines(roughnesses, cos_e, dots[0], dots[1], weight, out, scratch, view_sq, dots[2])
    add_factors(sums, cells, out, first_factor)


def add_factors(
    sums: torch.Tensor, cells: torch.Tensor, factors: torch.Tensor | tuple[torch.Tensor, ...], first_factor: int
) -> None:
    """Add `factors` (F, P, M) (or F (P, M) tensors) into `sums` (F S,) (flat (F, S) sums) at the
    cells `cells` (P M,) int64 of each factor's S, from factor `first_factor` on."""
    stride = sums.shape[0] // len(factors)
    for factor in range(first_factor, len(factors)):
        if torch.compiler.is_compiling():
            sums.index_add_(0, cells + factor * stride, factors[factor].reshape(-1))
        else:  # eager: into the factor's view, no shifted cells; scatter_add_ (the same sums bit
            # for bit) is ~0.6 ns per entry on one core against ~1.1 for index_add_ (cells in cache)
            sums[factor * stride : (factor + 1) * stride].scatter_add_(0, cells, factors[factor].reshape(-1))


def _fresh_work(like: torch.Tensor, num_factors: int) -> tuple[tuple[torch.Tensor, ...], ...]:
    """Work blocks as `work_blocks` gives them, but each (P, M) block a tensor of its own: traced
    by torch.compile, writes into views of one buffer would become scatters into all of it."""
    return tuple(tuple(like.new_empty(like.shape) for _ in range(count)) for count in (num_factors, 4, 3))


def _grid_block_fresh(
    node_points: torch.Tensor,
    nodes: torch.Tensor,
    geometry: torch.Tensor,
    position: torch.Tensor | None,
    roughnesses: tuple[torch.Tensor, ...],
    cos_e: torch.Tensor,
    view_sq: torch.Tensor,
    weight: torch.Tensor,
    out: torch.Tensor,
) -> None:
    """`grid_block` with work blocks of its own (compiled, they become the fused loops'
    registers), then copied into `out` (torch.compile takes no strided `out=` tensors)."""
    work = _fresh_work(weight, out.shape[0])
    grid_block(node_points, nodes, geometry, position, roughnesses, cos_e, view_sq, weight, work[0], work)
    out.copy_(torch.stack(work[0]))


def _dense_block_fresh(
    node_points: torch.Tensor,
    node: torch.Tensor,
    geometry: torch.Tensor,
    position: torch.Tensor | None,
    roughnesses: tuple[torch.Tensor, ...],
    cos_e: torch.Tensor,
    view_sq: torch.Tensor,
    weight: torch.Tensor,
    cells: torch.Tensor,
    sums: torch.Tensor,
    first_factor: int,
    num_factors: int,
) -> None:
    """`dense_block` with work blocks of its own (F = `num_factors`)."""
    dense_block(
        node_points,
        node,
        geometry,
        position,
        roughnesses,
        cos_e,
        view_sq,
        weight,
        cells,
        sums,
        first_factor,
        _fresh_work(weight, num_factors),
    )


@functools.cache
def compiled(function: Callable) -> Callable:
    """`torch.compile(function)` (inductor, dynamic shapes, one graph), made once per process."""
    return torch.compile(function, dynamic=True, fullgraph=True)


class BlockEvaluator:
    """Runs `grid_block` and `dense_block` on blocks, eagerly (reusing one work buffer) or
    compiled (`CutsRelightSettings.compiled`: compiled on first use per variant, then reused; a
    failure to compile, e.g. no C++ compiler, is a `RelightError`).

    Variants compiled per process: grid and dense blocks, per mode (env, indirect), factor count,
    first added factor and one-wide rows (the relighter's entries gathered one per line; torch
    specialises sizes 0 and 1). A block of one row runs eagerly (it would be one more variant for
    a few hundred entries at most); empty blocks are skipped.

    Args:
        num_factors: F, the factors per entry (4, or 6 with a clearcoat).
        dtype, device: of the factors.
        compiled: use `torch.compile`.
    """

    def __init__(self, num_factors: int, dtype: torch.dtype, device: torch.device, compiled: bool):
        self._flat = torch.empty(0, dtype=dtype, device=device)
        self._num_factors = num_factors
        self._compiled = compiled

    def _work(self, rows: int, width: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        size = (self._num_factors + 7) * rows * width
        if self._flat.numel() < size:
            self._flat = self._flat.new_empty(size)
        return work_blocks(self._flat, self._num_factors, rows, width)

    def grid(
        self,
        node_points: torch.Tensor,
        nodes: torch.Tensor,
        geometry: torch.Tensor,
        position: torch.Tensor | None,
        roughnesses: tuple[torch.Tensor, ...],
        cos_e: torch.Tensor,
        view_sq: torch.Tensor,
        weight: torch.Tensor,
        out: torch.Tensor,
    ) -> None:
        """`grid_block` (arguments as there)."""
        arguments = (node_points, nodes, geometry, position, roughnesses, cos_e, view_sq, weight, out)
        if weight.numel() == 0:
            return
        if self._compiled and weight.shape[0] > 1:
            _run_compiled(_grid_block_fresh, arguments)
        else:
            grid_block(*arguments, self._work(*weight.shape))

    def dense(
        self,
        node_points: torch.Tensor,
        node: torch.Tensor,
        geometry: torch.Tensor,
        position: torch.Tensor | None,
        roughnesses: tuple[torch.Tensor, ...],
        cos_e: torch.Tensor,
        view_sq: torch.Tensor,
        weight: torch.Tensor,
        cells: torch.Tensor,
        sums: torch.Tensor,
        first_factor: int,
    ) -> None:
        """`dense_block` (arguments as there)."""
        arguments = (
            node_points,
            node,
            geometry,
            position,
            roughnesses,
            cos_e,
            view_sq,
            weight,
            cells,
            sums,
            first_factor,
        )
        if weight.numel() == 0:
            return
        if self._compiled and weight.shape[0] > 1:
            _run_compiled(_dense_block_fresh, (*arguments, self._num_factors))
        else:
            dense_block(*arguments, self._work(*weight.shape))


def _run_compiled(function: Callable, arguments: tuple) -> None:
    """`compiled(function)(*arguments)`; a failure of torch.compile is a one-line `RelightError`."""
    try:
        # Never eager behind our back: past the limit on variants torch.compile would fall back.
        with torch._dynamo.config.patch(fail_on_recompile_limit_hit=True, recompile_limit=64):
            compiled(function)(*arguments)
    except torch._dynamo.exc.TorchDynamoException as error:
        cause = getattr(error, "inner_exception", None) or error
        reason = (str(cause).strip().splitlines() or [""])[0]
        raise RelightError(
            f"CutsRelightSettings(compiled=True): torch.compile of the cuts' BRDF blocks failed "
            f"({type(cause).__name__}: {reason}); set compiled=False"
        ) from error
