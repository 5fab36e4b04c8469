"""Long lighting sessions: random edits of every kind (lights added and removed too) on one open
relighter of each method hold its memory level and its answers.

The default suite makes a few hundred edits per method on tiny caches; the 10,000-edit run is
`python -m pipeline.benchmarks.long_session --edits 10000` (docs/ERRORS.md has its figures).
"""

from __future__ import annotations

import os

import pytest

from fuzz_support import METHODS, bake_all
from pipeline.benchmarks.long_session import EDIT_KINDS, run_session

NUM_EDITS = 2000 if os.environ.get("HYPOTHESIS_PROFILE") == "nightly" else 300
MAX_GROWTH = 0.05
"""Anonymous RSS growth allowed after the first tenth of the edits."""
MAX_DIFFERENCE = 1e-5
"""Largest |kept - fresh| pixel difference, relative to the image's peak: float32 rounding of sums
taken in another order (measured near 7e-8)."""


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    return bake_all(tmp_path_factory.mktemp("session_bakes"))


@pytest.mark.slow
@pytest.mark.parametrize("method", METHODS)
def test_long_session_holds_memory_and_matches_a_fresh_relighter(baked, method):
    report = run_session(baked[method], NUM_EDITS, num_checkpoints=3, seed=METHODS.index(method))
    assert all(report.kinds[kind] > 0 for kind in EDIT_KINDS), report.kinds
    assert len(report.checkpoint_errors) == 3
    assert max(report.checkpoint_errors) <= MAX_DIFFERENCE, report.checkpoint_errors
    assert report.growth_after(0.1) < MAX_GROWTH, report.rss
