"""`relight bench-direct` on a tiny bake: every case runs, each edit kind recomputes exactly its
stage (the relighter's pass counters), and the edit-kind table and CSV carry them. No timing is
asserted: speed lives in the benchmark's output, not in tests."""

from __future__ import annotations

import csv

import pytest

from pipeline.benchmarks.direct import EDIT_KINDS, edit_kind_rows, format_table, run_benchmark, write_csv
from relight_torch.direct.settings import RelightSettings

# kind -> (visibility, shading, masks) passes one edit of one light runs.
EXPECTED_PASSES = {"colour": (0, 0, 0), "shaping": (0, 1, 0), "move": (1, 1, 0), "link": (0, 0, 1)}


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    return run_benchmark(
        "cornell_box",
        16,
        16,
        repeats=2,
        settings=RelightSettings(area_samples=4),
        work_dir=tmp_path_factory.mktemp("bench"),
    )


def test_each_edit_kind_recomputes_its_stage_only(report):
    kinds = dict(edit_kind_rows(report))
    assert list(kinds) == list(EDIT_KINDS)
    for kind, (visibility, shading, masks) in EXPECTED_PASSES.items():
        row = kinds[kind]
        assert (row.visibility_passes, row.shading_passes, row.mask_passes) == (visibility, shading, masks), kind


def test_table_and_csv_list_every_case(report, tmp_path):
    table = format_table(report)
    assert "edit kinds" in table
    kind_lines = table.split("edit kinds", 1)[1].splitlines()
    for kind in EDIT_KINDS:
        assert any(line.startswith(kind) for line in kind_lines), kind
    path = tmp_path / "bench.csv"
    write_csv(report, path)
    with open(path, newline="") as handle:
        rows = [row for row in csv.reader(handle) if row and not row[0].startswith("#")]
    assert rows[0][:3] == ["case", "num_lights", "median_ms"] and "mask_passes" in rows[0]
    assert [row[0] for row in rows[1:]] == [row.case for row in report.rows]
