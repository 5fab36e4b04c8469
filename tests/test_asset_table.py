"""The real-asset table in its reduced form (`pipeline.benchmarks.asset_table`): tiny images, few
reference samples. Every suite asset bakes and relights with the direct method, and every method
and the shot cache bake and relight the exterior shot (sky in the top half of the frame); no cell
may fail or be a traceback."""

from __future__ import annotations

import math

import pytest

from pipeline.benchmarks.asset_table import METHODS, measure_cell, table_markdown
from pipeline.benchmarks.suite_assets import SUITE

SIZE = (16, 12)
SPP = 16
# A 16 x 12 frame against a 16-sample reference: the reference's noise bounds the PSNR.
MIN_PSNR = 25.0


def _check(cell) -> None:
    assert cell.baked and cell.rendered and cell.error == "", cell
    assert math.isfinite(cell.psnr) and cell.psnr > MIN_PSNR, cell
    assert cell.cache_bytes > 0 and cell.bake_seconds > 0 and cell.render_seconds > 0


@pytest.mark.slow
@pytest.mark.parametrize("asset", SUITE, ids=[a.name for a in SUITE])
def test_every_asset_bakes_and_relights(asset, tmp_path):
    _check(measure_cell(asset, "direct", SIZE, tmp_path, SPP))


@pytest.mark.slow
@pytest.mark.parametrize("method", METHODS)
def test_every_method_bakes_and_relights_the_exterior(method, tmp_path):
    exterior = next(a for a in SUITE if a.name == "exterior_teapots")
    cell = measure_cell(exterior, method, SIZE, tmp_path, SPP)
    _check(cell)
    assert f"| exterior_teapots | {method} | 16x12 | yes |" in table_markdown([cell], "test", SPP)
