"""`relight bench --quick`: the CSV/JSON rows, the comparison rows, the charts, determinism."""

from __future__ import annotations

import math

import pytest

from pipeline.bake.adapter import format_params
from pipeline.benchmarks.bench.chart import pareto_front
from pipeline.benchmarks.bench.comparison import SppCurve
from pipeline.benchmarks.bench.methods import adapters
from pipeline.benchmarks.bench.runner import BenchConfig, run_bench
from pipeline.benchmarks.rows import COLUMNS, SweepRow, parse_params, read_csv, read_json
from pipeline.cli import main

COMPARISONS = ("reference-equal-time", "reference-full")


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    assert main(["bench", "--quick", "--out", str(out)]) == 0
    return out


def test_csv_has_the_shared_columns_and_one_row_per_point_and_edit(quick):
    assert (quick / "bench.csv").read_text().splitlines()[0] == ",".join(COLUMNS)
    rows = read_csv(quick / "bench.csv")
    registered = adapters()
    assert {row.method for row in rows} == set(registered) | set(COMPARISONS)
    edits = {"shot", "move", "white_light", "focus"}
    for name, adapter in registered.items():
        method_rows = [row for row in rows if row.method == name]
        variants = {row.params for row in method_rows}
        assert len(variants) >= len(adapter.grid(True))
        assert len(method_rows) == len(variants) * len(edits)
        assert {(row.params, row.light_edit) for row in method_rows} == {(p, e) for p in variants for e in edits}
        for row in method_rows:
            assert (row.scene, row.width, row.height, row.device) == ("cornell_box", 24, 24, "cpu")
            for value in (row.psnr_db, row.rel_mse, row.cache_bytes, row.bake_s, row.relight_ms):
                assert math.isfinite(value) and value > 0, row
            # Measured 27-32 dB at 24x24 against a 32-spp reference (its own noise dominates).
            assert row.psnr_db > 24, row
            assert math.isnan(row.psnr_indirect_db) == (adapter.bounces(adapter.grid(True)[0]) == 0), row


def test_json_holds_the_csv_rows_and_the_fits(quick):
    csv_rows, json_rows = read_csv(quick / "bench.csv"), read_json(quick / "bench.json")
    assert [(r.method, r.params, r.light_edit) for r in csv_rows] == [
        (r.method, r.params, r.light_edit) for r in json_rows
    ]
    for a, b in zip(csv_rows, json_rows, strict=True):
        assert a.psnr_db == pytest.approx(b.psnr_db, rel=1e-5, nan_ok=True)


def test_comparison_rows_pair_every_timed_shot_row(quick):
    rows = read_csv(quick / "bench.csv")
    timed = [r for r in rows if r.method not in COMPARISONS and r.light_edit == "shot"]
    for kind in COMPARISONS:
        compared = [r for r in rows if r.method == kind]
        assert sorted(r.params.split(" spp=")[0] for r in compared) == sorted(
            f"vs={r.method} {r.params}" for r in timed
        )
    for row in (r for r in rows if r.method == "reference-full"):
        method = next(r for r in timed if f"vs={r.method} {r.params}" == row.params.split(" spp=")[0])
        parameters = row.parameters()
        assert float(parameters["spp"]) > 0 and parameters["bound"] in ("fit", "lower")
        assert float(parameters["speedup"]) == pytest.approx(row.relight_ms / method.relight_ms, rel=1e-3)
        assert row.psnr_db == pytest.approx(method.psnr_db, rel=1e-5)
    for row in (r for r in rows if r.method == "reference-equal-time"):
        assert math.isfinite(row.psnr_db) and float(row.parameters()["spp"]) > 0


def test_summary_has_each_methods_best_speedup(quick):
    lines = (quick / "summary.txt").read_text().splitlines()
    assert lines[0].split()[:2] == ["scene", "method"]
    assert sorted(line.split()[1] for line in lines[1:]) == sorted(adapters())


def test_charts_are_png_files(quick):
    for name in ["speed_accuracy"] + [f"params_{method}" for method in adapters()]:
        data = (quick / f"{name}.png").read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000, name


def test_psnr_is_deterministic_across_runs(quick, tmp_path):
    again = run_bench(BenchConfig.quick_run(tmp_path, methods=("direct",)), log=lambda line: None)
    first = {(r.params, r.light_edit): r.psnr_db for r in read_json(quick / "bench.json") if r.method == "direct"}
    assert {(r.params, r.light_edit): r.psnr_db for r in again.rows if r.method == "direct"} == first


def test_pareto_front_keeps_undominated_points_by_time():
    curve = [("a", 30.0, 10.0), ("b", 29.0, 20.0), ("c", 35.0, 40.0), ("d", 34.0, 50.0), ("e", 36.0, float("nan"))]
    assert [p[0] for p in pareto_front(curve)] == ["a", "c"]


def test_spp_curve_inverts_its_own_prediction():
    curve = SppCurve(0, (1, 4), (0.1, 0.4), (0.02, 0.005), 64, 6.4, noise=0.02, seconds_per_spp=0.1, seconds_fixed=0)
    assert curve.spp_for(curve.mse_at(8.0)) == pytest.approx(8.0)
    assert math.isinf(curve.spp_for(0.5 * curve.noise / 64))


def test_params_round_trip_and_reject_separators():
    assert parse_params(format_params({"gathers": 1024, "encoding": "float16"})) == {
        "gathers": "1024",
        "encoding": "float16",
    }
    with pytest.raises(ValueError, match="must not contain"):
        format_params({"name": "a b"})
    assert SweepRow("direct", "s", 1, 1, "shot", "").parameters() == {}
