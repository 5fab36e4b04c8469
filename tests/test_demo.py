"""`relight demo` (the README's first command) writes what it promises, on a tiny image."""

from __future__ import annotations

import csv
import math

from pipeline.cli import main
from relight_torch.io.exr import read_rgb_exr


def test_demo_writes_images_summary_and_chart(tmp_path):
    assert (
        main(["demo", "--out", str(tmp_path), "--width", "24", "--height", "24", "--spp", "4", "--quality", "25"]) == 0
    )
    with open(tmp_path / "summary.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert [row["edit"] for row in rows] == ["shot", "move", "white_light", "focus", "new_light"]
    for row in rows:
        assert math.isfinite(float(row["psnr_db"])) and float(row["render_ms"]) > 0
        assert 0.5 < float(row["energy_ratio"]) < 2.0
        for kind in ("relit", "reference"):
            assert read_rgb_exr(tmp_path / f"{row['edit']}.{kind}.exr").shape == (24, 24, 3)
            assert (tmp_path / f"{row['edit']}.{kind}.png").stat().st_size > 0
    assert (tmp_path / "chart.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
