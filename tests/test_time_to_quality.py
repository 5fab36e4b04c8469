"""`relight bench --progressive` (`pipeline.benchmarks.bench.time_to_quality`): the curves of PSNR
against time after a light edit for the relighter's progressive frames and the path tracers, and the
speed-up at equal PSNR read off them."""

from __future__ import annotations

import csv
import math

import pytest

from pipeline import cli
from pipeline.benchmarks.bench.time_to_quality import Point, pass_spp, path_time_to, speedups, time_to
from pipeline.scenes import SCENES


def _pass(spp: int, ms: float, db: float) -> Point:
    return Point("path tracer (ours)", "move", str(spp), ms, ms, db)


def test_passes_double_the_spp():
    assert pass_spp(1) == [1]
    assert pass_spp(16) == [1, 1, 2, 4, 8]
    assert sum(pass_spp(100)) == 64


def test_path_time_interpolates_mse_in_one_over_spp():
    # MSE = 1e-3 / spp exactly: 30 dB at 1 spp, 33.01 dB at 2, 36.02 dB at 4.
    passes = [_pass(spp, 100.0 * spp, -10 * math.log10(1e-3 / spp)) for spp in (1, 2, 4)]
    assert path_time_to(passes, 30.0, "cpu_ms") == (100.0, False)
    ms, extrapolated = path_time_to(passes, 35.0, "cpu_ms")  # 10^0.5 = 3.16 spp: 316 ms
    assert not extrapolated and ms == pytest.approx(100.0 * 10**0.5, rel=1e-6)
    ms, extrapolated = path_time_to(passes, 40.0, "cpu_ms")  # 10 spp, past the last pass
    assert extrapolated and ms == pytest.approx(1000.0, rel=1e-6)


def test_speedup_is_the_path_tracers_time_over_the_relighters():
    frames = [
        Point("relighter", "move", "1/16", 10.0, 8.0, 31.0),
        Point("relighter", "move", "exact", 500.0, 400.0, 36.0),
    ]
    passes = [_pass(spp, 100.0 * spp, -10 * math.log10(1e-3 / spp)) for spp in (1, 2, 4)]
    assert time_to(frames, 30.0, "elapsed_ms") == 10.0 and time_to(frames, 40.0, "elapsed_ms") is None
    rows = speedups(frames + passes, ["move"], ["relighter"], ["path tracer (ours)"], "elapsed_ms")
    by_level = {row["level_db"]: row for row in rows}
    assert by_level[30.0]["speedup"] == pytest.approx(10.0)
    assert by_level[35.0]["speedup"] == pytest.approx(100.0 * 10**0.5 / 500.0)
    assert by_level[40.0]["speedup"] is None and "never reaches" in by_level[40.0]["note"]


def test_unknown_edit_is_one_error_line(tmp_path, capsys):
    assert cli.main(["bench", "--progressive", "--out", str(tmp_path), "--edits", "dome turn"]) == 2
    assert capsys.readouterr().err.strip().count("\n") == 0


@pytest.mark.slow
def test_bench_progressive_writes_curves_and_speedups(tmp_path):
    shot = SCENES["cornell_box"].write(tmp_path / "scene")
    layers = {}
    options = {
        "direct": ["--supersampling", "2"],
        "transfer": ["--supersampling", "2", "--gathers", "16", "--coefficients", "8", "--bounces", "2"]
        + ["--bounce-coefficients", "4"],
    }
    for method, extra in options.items():
        out = tmp_path / method
        arguments = ["bake", str(shot), "--camera", SCENES["cornell_box"].camera, "--out", str(out), "--method", method]
        assert cli.main(arguments + ["--width", "32", "--height", "24", "--texture-samples", "1", *extra]) == 0
        layers[method] = str(next(out.glob("*.relight.usda")))
    out = tmp_path / "curves"
    arguments = ["bench", "--progressive", "--out", str(out), "--width", "32", "--height", "24", "--spp", "8"]
    arguments += ["--reference-size", "16", "12", "--path-spp", "2", "--mitsuba-spp", "1", "--edits", "move"]
    arguments += ["--shot-cache", layers["transfer"], "--direct-cache", layers["direct"], "--work", str(tmp_path / "w")]
    assert cli.main(arguments) == 0
    with open(out / "time_to_quality.csv") as handle:
        points = list(csv.DictReader(handle))
    renderers = {row["renderer"] for row in points}
    assert {"relighter, shot sizes (transfer)", "relighter, direct", "path tracer (ours)"} <= renderers
    relit = [row for row in points if row["renderer"] == "relighter, direct"]
    assert relit[-1]["step"] == "exact" and all(float(row["psnr_db"]) > 5 for row in relit)
    traced = [row for row in points if row["renderer"] == "path tracer (ours)"]
    assert [row["step"] for row in traced] == ["1", "2"]
    assert (out / "time_to_quality.png").stat().st_size > 0 and "Speed-up" in (out / "time_to_quality.md").read_text()
    with open(out / "time_to_quality_speedups.csv") as handle:
        assert len(list(csv.DictReader(handle))) == 2 * 2 * 3 * len(
            renderers - {"relighter, shot sizes (transfer)", "relighter, direct"}
        )
