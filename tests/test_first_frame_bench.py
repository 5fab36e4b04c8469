"""`pipeline.benchmarks.first_frame` on the tiny caches: a row per cache and edit kind, the edit
kinds a relighter lacks listed from its declared capability, the others measured."""

from __future__ import annotations

import pytest

from pipeline.benchmarks import first_frame
from pipeline.benchmarks.tiny_caches import bake_tiny


@pytest.mark.slow
def test_every_edit_kind_on_every_cache(tmp_path):
    layers = bake_tiny(tmp_path / "caches", ("transfer", "direct", "cuts", "multiview"))
    out = tmp_path / "first_frame.md"
    arguments = ["--shot-cache", str(layers["transfer"]), "--direct-cache", str(layers["direct"])]
    arguments += ["--cache", str(layers["cuts"]), str(layers["multiview"]), "--repeats", "1", "--threads", "1"]
    assert first_frame.main([*arguments, "--work", str(tmp_path / "work"), "--out", str(out)]) == 0
    rows = {
        tuple(cell.strip() for cell in line.split("|")[1:3]): [cell.strip() for cell in line.split("|")[3:-1]]
        for line in out.read_text().splitlines()
        if line.startswith("| ") and not line.startswith("| cache")
    }
    caches = ("shot sizes (transfer)", "direct", "cuts", "multiview")
    assert set(rows) == {(cache, edit) for cache in caches for edit in first_frame.EDITS}
    for cache in caches:
        for edit in first_frame.LIGHT_EDITS:  # every relighter takes light edits
            level, cpu_ms, wall_ms, db = rows[cache, edit]
            assert level == ("whole" if cache in ("cuts", "multiview") else "1/16")
            assert float(cpu_ms) > 0 and float(wall_ms) > 0 and float(db) > 0
    for edit in ("material colour", "material roughness"):
        assert rows["cuts", edit][0] == "whole"
        level, cpu_ms, wall_ms, db = rows["direct", edit]
        assert level == "1/16" and float(cpu_ms) > 0 and float(wall_ms) > 0 and float(db) > 0
        for cache in ("shot sizes (transfer)", "multiview"):
            assert rows[cache, edit][0] == "not supported: material_edits is False"
    level, cpu_ms, wall_ms, db = rows["multiview", "camera move"]
    assert level == "1/16" and float(cpu_ms) > 0 and float(wall_ms) > 0 and 0 < float(db) < float("inf")
    for cache in ("shot sizes (transfer)", "direct", "cuts"):
        assert rows[cache, "camera move"][0] == "not supported: renders its baked camera only (needs_view is False)"
