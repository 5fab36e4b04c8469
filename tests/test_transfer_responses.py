"""Truncated wavelet rows refitted to their probe lights (`relight_torch.transfer.responses`)."""

from __future__ import annotations

import math

import pytest
import torch

from relight_torch.transfer.haar import haar2d
from relight_torch.transfer.responses import dense_responses, refit_rows, sparse_responses
from relight_torch.transfer.sparse import keep_top_k

SIDE = 16


def _rows(num_rows: int, channels: int, seed: int = 0) -> torch.Tensor:
    """(R, n, n, C) positive rows with near-field peaks on a smooth floor, as F rows look."""
    generator = torch.Generator().manual_seed(seed)
    grid = torch.stack(torch.meshgrid(torch.arange(SIDE), torch.arange(SIDE), indexing="ij"), -1).double()
    centre = torch.rand(num_rows, 1, 1, 2, generator=generator, dtype=torch.float64) * SIDE
    peak = 1.0 / (1.0 + ((grid - centre) ** 2).sum(-1))
    floor = 0.05 * torch.rand(num_rows, SIDE, SIDE, generator=generator, dtype=torch.float64)
    return (peak + floor).unsqueeze(-1).expand(-1, -1, -1, channels).contiguous()


def _light(peak: tuple[float, float]) -> torch.Tensor:
    """(n^2,) a lamp's patch on the gathers: bright around `peak`, smooth falloff."""
    grid = torch.stack(torch.meshgrid(torch.arange(SIDE), torch.arange(SIDE), indexing="ij"), -1).double()
    return 1.0 / (1.0 + 0.05 * ((grid - torch.tensor(peak)) ** 2).sum(-1)).reshape(-1)


def _wavelet(light: torch.Tensor) -> torch.Tensor:
    return haar2d(light.reshape(SIDE, SIDE, 1)).reshape(-1)


def test_top_k_keeps_each_rows_sum_so_uniform_light_loses_nothing():
    # The Haar box coefficient ranks first and every other basis function sums to zero: culling
    # cannot lose the light of a uniformly lit scene. What it loses comes from non-uniform light.
    dense = _rows(64, 1)
    kept = keep_top_k(haar2d(dense), 10)
    uniform = _wavelet(torch.ones(SIDE * SIDE, dtype=torch.float64)).unsqueeze(0)
    truncated = sparse_responses(kept, uniform)
    assert torch.allclose(truncated[:, 0, 0], dense.sum((1, 2))[:, 0], rtol=1e-12)


def test_refit_rows_transfer_their_probe_lights_exactly():
    dense = _rows(64, 1)
    coefficients = haar2d(dense)
    probes = torch.stack([_wavelet(_light((3.0, 4.0))), _wavelet(_light((12.0, 9.0)))])
    kept = keep_top_k(coefficients, 12)
    target = dense_responses(coefficients, probes)
    before = sparse_responses(kept, probes) / target
    refitted = refit_rows(kept, probes, target)
    after = sparse_responses(refitted, probes) / target
    # Plain top-k misses a share of a lamp's light on these rows; the refit rows none.
    assert float((before - 1).abs().max()) > 0.01
    assert torch.allclose(after, torch.ones_like(after), atol=1e-9)
    # Only the kept values change: the layout (and so the cache's size) is the same.
    assert torch.equal(refitted.indices, kept.indices) and torch.equal(refitted.offsets, kept.offsets)


def test_refit_is_the_least_norm_correction_and_keeps_lights_near_the_probes_closer():
    dense = _rows(64, 3, seed=1)
    coefficients = haar2d(dense)
    probe = _wavelet(_light((5.0, 5.0))).unsqueeze(0)
    kept = keep_top_k(coefficients, 12)
    refitted = refit_rows(kept, probe, dense_responses(coefficients, probe))
    # Least norm: the correction of each row lies in the span of the probe at its kept indices.
    delta = refitted.values - kept.values
    row_of = torch.repeat_interleave(torch.arange(64), kept.offsets.diff())
    at = probe[0][kept.indices.long()]
    for row in range(0, 64, 9):
        mine = row_of == row
        direction = at[mine] / at[mine].norm()
        residual = delta[mine, 0] - direction * (direction @ delta[mine, 0])
        assert float(residual.norm()) <= 1e-9 * max(1.0, float(delta[mine, 0].norm()))
    # A lamp moved by a gather keeps far more of its energy than with plain top-k.
    moved = _wavelet(_light((6.0, 5.0))).unsqueeze(0)
    exact = dense_responses(coefficients, moved)
    plain_error = float(((sparse_responses(kept, moved) - exact) / exact).abs().mean())
    refit_error = float(((sparse_responses(refitted, moved) - exact) / exact).abs().mean())
    assert refit_error < 0.5 * plain_error


def test_refit_rows_ignores_zero_probes_and_checks_shapes():
    dense = _rows(8, 1)
    coefficients = haar2d(dense)
    probes = torch.stack([torch.zeros(SIDE * SIDE, dtype=torch.float64), _wavelet(_light((2.0, 2.0)))])
    kept = keep_top_k(coefficients, 6)
    refitted = refit_rows(kept, probes, dense_responses(coefficients, probes))
    assert torch.isfinite(refitted.values).all()
    assert torch.allclose(sparse_responses(refitted, probes[1:]), dense_responses(coefficients, probes[1:]))
    with pytest.raises(ValueError, match="probes"):
        refit_rows(kept, probes[:, :10], dense_responses(coefficients, probes))
    with pytest.raises(ValueError, match="target"):
        refit_rows(kept, probes, dense_responses(coefficients, probes)[:, :1])
    assert math.isclose(float(dense_responses(coefficients, probes)[0, 0, 0]), 0.0)
