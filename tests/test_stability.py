"""The stability suite: each method's known failure cases, measured against the path tracer.

Every image must be finite and reach the case's honest PSNR bound (`StabilityCase.min_psnr`, the
measured value less about 2 dB); docs/STABILITY.md holds the measured table.
"""

from __future__ import annotations

import math

import pytest

from pipeline.benchmarks.bench.stability import CASES, StabilityRun, write_doc

PAIRS = [(case, method) for case in CASES for method in case.why]


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    run = StabilityRun(tmp_path_factory.mktemp("stability"))
    return {(r.case, r.method): r for r in run.run()}


@pytest.mark.parametrize("case, method", PAIRS, ids=[f"{case.name}-{method}" for case, method in PAIRS])
def test_case_is_finite_and_within_its_bound(results, case, method):
    result = results[(case.name, method)]
    assert result.finite, f"{case.name} {method}: NaN or Inf in the relit image"
    assert math.isfinite(result.rel_mse)
    assert result.psnr_db >= case.min_psnr[method], (case.name, method, result.psnr_db)


@pytest.mark.parametrize("method", ["direct", "transfer", "gather"])
def test_a_light_inside_closed_geometry_does_not_leak(results, method):
    # The hidden light adds nothing to the reference; a leak would show as a drop from the baseline.
    assert results[("inside_geometry", method)].psnr_db >= results[("baseline", method)].psnr_db - 0.5


def test_doc_has_a_row_and_a_sentence_per_case_and_method(results, tmp_path):
    path = tmp_path / "STABILITY.md"
    write_doc(list(results.values()), path, "python -m pipeline.benchmarks.bench.stability")
    text = path.read_text()
    for case, method in PAIRS:
        assert f"| {case.name} | {method} |" in text and case.why[method] in text
