"""The exterior benchmark's child processes (`pipeline.benchmarks.exterior.run_child`): each peak
resident set is that child's own, and a failing child is one line."""

from __future__ import annotations

import pytest

from pipeline.benchmarks.exterior import run_child


def test_each_child_reports_its_own_peak():
    _, small, printed = run_child("timeit", ["-n", "1", "-r", "1", "pass"])
    _, big, _ = run_child("timeit", ["-n", "1", "-r", "1", "b'x' * 400_000_000"])
    assert "1 loop" in printed
    assert big > small + 0.38
    # A parent holding more than either child: wait4's ru_maxrss would report the parent's
    # resident set at the spawn for both.
    held = b"x" * 1_000_000_000
    _, again, _ = run_child("timeit", ["-n", "1", "-r", "1", "pass"])
    assert len(held) and again < small + 0.1


def test_a_failing_child_is_one_line():
    with pytest.raises(RuntimeError, match=r"^pipeline.cli bake: relight: error: .*missing.usda"):
        run_child("pipeline.cli", ["bake", "missing.usda", "--camera", "/C", "--out", "out"])
