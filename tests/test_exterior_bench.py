"""The exterior benchmark: its child processes (`run_child`) each report their own peak resident
set, a failing child is one line, and rows an earlier run measured stay marked with its command."""

from __future__ import annotations

import pytest

from pipeline.benchmarks.exterior import SESSION, Row, read_rows, run_child, summary, write_rows


def test_each_child_reports_its_own_peak(tmp_path):
    log = tmp_path / "child.log"
    _, small, printed = run_child("timeit", ["-n", "1", "-r", "1", "pass"], log)
    _, big, _ = run_child("timeit", ["-n", "1", "-r", "1", "b'x' * 400_000_000"], log)
    assert "1 loop" in printed
    assert big > small + 0.38
    # A parent holding more than either child: wait4's ru_maxrss would report the parent's
    # resident set at the spawn for both.
    held = b"x" * 1_000_000_000
    _, again, _ = run_child("timeit", ["-n", "1", "-r", "1", "pass"], log)
    assert len(held) and again < small + 0.1


def test_a_failing_child_is_one_line_and_its_log_is_kept(tmp_path):
    log = tmp_path / "logs" / "bake.log"
    with pytest.raises(RuntimeError, match=r"^pipeline.cli bake: relight: error: .*missing.usda"):
        run_child("pipeline.cli", ["bake", "missing.usda", "--camera", "/C", "--out", "out"], log)
    assert "relight: error: " in log.read_text()


def test_rows_of_an_earlier_run_keep_its_command(tmp_path):
    earlier = Row("640x480", "shot", 1221.0, 10.29, 6 * 10**8, "direct+transfer", dict.fromkeys(SESSION, 1.5), "old")
    now = Row("1920x1080", "shot", 2000.0, 9.5, 10**9, "direct+transfer", dict.fromkeys(SESSION, 2.0), "new")
    write_rows(tmp_path / "exterior.csv", [earlier, now])
    assert read_rows(tmp_path / "exterior.csv") == [earlier, now]
    assert read_rows(tmp_path / "missing.csv") == []
    table = summary([earlier, now], [], 1000, "new", (1.0, 1.0))
    assert "| 640x480* | shot | 1221 | 10.29 |" in table and "| 1920x1080 | shot |" in table
    assert "* Measured by an earlier run (`--keep-earlier`), on its own: `old`." in table
