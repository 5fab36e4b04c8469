"""Shared test options and fixtures.

`--device cpu|cuda` picks where torch kernels run (default cpu); CUDA tests skip on machines
without a GPU. `TOLERANCES` is the one table of per-dtype tolerances for comparisons of values
that should agree up to rounding (not Monte Carlo estimates: those use their measured standard
error).
"""

from __future__ import annotations

import os

import pytest
import torch

import relight_torch  # noqa: F401  registers the USD schemas before any test opens a stage

if os.environ.get("PYTEST_XDIST_WORKER"):
    # One torch thread per xdist worker: -n auto already runs a worker per core, and torch's own
    # threads spinning against each other made the suite ~15x slower on 2 busy cores.
    torch.set_num_threads(1)

TOLERANCES = {
    torch.float32: {"rtol": 1e-5, "atol": 1e-6},
    torch.float64: {"rtol": 1e-10, "atol": 1e-12},
}


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--device", default="cpu", help="torch device for kernel tests: cpu or cuda")


@pytest.fixture
def device(request: pytest.FixtureRequest) -> torch.device:
    """The torch device named by `--device`; skips the test when CUDA is asked for but absent."""
    chosen = torch.device(request.config.getoption("--device"))
    if chosen.type == "cuda" and not torch.cuda.is_available():
        pytest.skip("--device cuda given but CUDA is not available")
    return chosen


@pytest.fixture
def tolerances() -> dict[torch.dtype, dict[str, float]]:
    """`TOLERANCES`, for `torch.testing.assert_close(..., **tolerances[dtype])`."""
    return TOLERANCES
