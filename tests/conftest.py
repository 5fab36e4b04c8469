"""Shared test options, fixtures and the checks made before any test runs.

`--device cpu|cuda` picks where torch kernels run (default cpu); CUDA tests skip on machines
without a GPU. `TOLERANCES` is the one table of per-dtype tolerances for comparisons of values
that should agree up to rounding (not Monte Carlo estimates: those use their measured standard
error).

Before collection, every declared test dependency must be installed at its pin and import
(`environment_support`): a broken install stops the run with one line naming the package. The
report's header names the C++ compiler torch.compile finds; tests that need one take the
`cxx_compiler` fixture, which skips, saying why, only where there is none.
"""

from __future__ import annotations

import os

import pytest
import torch

import environment_support
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


def pytest_configure(config: pytest.Config) -> None:
    if hasattr(config, "workerinput"):  # an xdist worker: the controller has checked already
        return
    requirements = environment_support.declared_test_requirements()
    problems = [p for p in map(environment_support.requirement_problem, requirements) if p is not None]
    if problems:
        raise pytest.UsageError("; ".join(problems))


def pytest_report_header(config: pytest.Config) -> str:
    return environment_support.describe_cxx_compiler()


@pytest.fixture(scope="session")
def cxx_compiler() -> str:
    """The C++ compiler torch.compile uses; skips the test on a machine without one."""
    compiler = environment_support.find_cxx_compiler()
    if compiler is None:
        pytest.skip("no C++ compiler: torch.compile's C++ backend needs one (set CXX or install g++)")
    return compiler


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
