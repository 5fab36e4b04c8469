"""The figures of docs/ERRORS.md's 'Fuzzed and faulted' section, measured by running what they describe.

    python -m pipeline.benchmarks.fault_figures --profile nightly --edits 10000 --write docs/ERRORS.md

runs the fuzz and fault tests (tests/test_fuzz_caches.py, test_fuzz_stages.py, test_faults.py)
under the hypothesis profile, each example appending what it tried and how it ended to a tally
file (tests/fuzz_support.py, RELIGHT_FAULT_TALLY); then the long session of
`pipeline.benchmarks.long_session` with EDITS edits per method. It prints the tables and, with
--write, replaces the text between each part's markers in that file (`--part tests` or
`--part sessions` measures and replaces one of the two).
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from pipeline.benchmarks.long_session import SessionReport, curve_csv, run_sessions
from pipeline.benchmarks.tiny_caches import METHODS
from relight_torch.io.atomic import write_text_atomic

FUZZ_TESTS = ("damaged cache", "bad lights layer", "bad shot")
"""The tallies (tests/fuzz_support.py `tally`) of generated inputs; the rest are faults."""
TESTS = ("tests/test_fuzz_caches.py", "tests/test_fuzz_stages.py", "tests/test_faults.py")
MARKERS = {
    "tests": ("<!-- fault-figures:start -->", "<!-- fault-figures:end -->"),
    "sessions": ("<!-- long-session:start -->", "<!-- long-session:end -->"),
}
CURVE_POINTS = 10
"""The memory curve's table samples the anonymous RSS at every tenth of the edits."""
ROOT = Path(__file__).resolve().parents[2]


def run_tests(profile: str, workers: int) -> tuple[list[dict], str, float]:
    """Run the fuzz and fault tests under `profile` -> (tally records, pytest's summary line, seconds)."""
    with tempfile.TemporaryDirectory(prefix="fault-figures-") as temp:
        tally = Path(temp) / "tally.jsonl"
        environment = {**os.environ, "HYPOTHESIS_PROFILE": profile, "RELIGHT_FAULT_TALLY": str(tally)}
        start = time.perf_counter()
        result = subprocess.run(
            [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", str(workers), *TESTS],
            cwd=ROOT,
            env=environment,
            capture_output=True,
            text=True,
        )
        seconds = time.perf_counter() - start
        summary = [line for line in result.stdout.splitlines() if " passed" in line or " failed" in line]
        records = [json.loads(line) for line in tally.read_text().splitlines()] if tally.exists() else []
    return records, (summary[-1].strip("= ") if summary else result.stdout[-300:]), seconds


def fuzz_table(records: list[dict]) -> list[str]:
    """Markdown rows: per fuzzed input and method, examples run, refused in one line, rendered finite."""
    counts = collections.Counter()
    for record in records:
        if record["test"] in FUZZ_TESTS:
            key = (record["test"], record["method"], record.get("damage", ""))
            counts[key + ("examples",)] += 1
            counts[key + ("refused" if record["refused"] else "rendered",)] += 1
    rows = [
        "| Input | Method | Damage | Examples | Refused (one line) | Rendered (finite) |",
        "|---|---|---|---|---|---|",
    ]
    for test, method, damage in sorted({key[:3] for key in counts}):
        key = (test, method, damage)
        rows.append(
            f"| {test} | {method} | {damage or '-'} | {counts[key + ('examples',)]} | "
            f"{counts[key + ('refused',)]} | {counts[key + ('rendered',)]} |"
        )
    return rows


def fault_table(records: list[dict]) -> list[str]:
    """Markdown rows of the kills and the readers."""
    rows = ["| Fault | Method | Tried | Outcome |", "|---|---|---|---|"]
    for record in records:
        if record["test"].startswith("disk full"):
            rows.append(
                f"| {record['test']} (file-size limit) | {record['method']} | 1 | one line, exit 2, nothing "
                f"left behind{'; the re-run bakes the same bytes' if 'bake' in record['test'] else ''} |"
            )
        elif record["test"] == "failed re-bake over a cache":
            rows.append(
                f"| a re-bake failing on a full disk over a good cache | {record['method']} | 1 | one line, exit 2; "
                "the old cache unchanged, valid, same image; the re-run replaces it |"
            )
        elif "kills" in record:
            rows.append(
                f"| SIGKILL at random moments of a bake | {record['method']} | {record['kills']} kill "
                f"point{'s' if record['kills'] > 1 else ''} ({record['landed']} landed before the bake "
                f"ended) | re-run equals the uninterrupted bake (same tree hash) |"
            )
        elif record["test"] == "readers during a re-bake":
            rows.append(
                f"| renders while a re-bake replaces the cache | {record['method']} | "
                f"{record['old'] + record['new'] + record['refused']} renders | {record['old']} old image, "
                f"{record['new']} new image, {record['refused']} refused in one line, none mixed |"
            )
    return rows


def settled_edit(edits: int) -> int:
    """The edit after which memory should have levelled off: the first 1,000 (a tenth of fewer)."""
    return min(1000, edits // 10)


def session_table(reports: dict[str, SessionReport], edits: int) -> list[str]:
    """Markdown rows of the long sessions: memory, its growth once settled, checkpoint differences."""
    settled = settled_edit(edits)
    rows = [
        f"| Method | Edits | Anonymous RSS at start | at edit {settled:,} | at end | Growth after edit {settled:,} | "
        "Total RSS at start, end | Edits per second | Largest checkpoint difference |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for method, report in reports.items():
        rows.append(
            f"| {method} | {edits:,} | {report.rss[0][1] / 2**20:.1f} MiB | {report.rss_at(settled) / 2**20:.1f} MiB | "
            f"{report.rss[-1][1] / 2**20:.1f} MiB | {100 * report.growth_after_edit(settled):+.2f} % | "
            f"{report.total_rss[0][1] / 2**20:.0f}, {report.total_rss[-1][1] / 2**20:.0f} MiB | "
            f"{edits / report.seconds:.0f} | {max(report.checkpoint_errors):.1e} |"
        )
    return rows


def curve_table(reports: dict[str, SessionReport], edits: int) -> list[str]:
    """Markdown rows of the memory curve: anonymous RSS (MiB) of each method at every tenth of the edits."""
    points = [round(edits * k / CURVE_POINTS) for k in range(CURVE_POINTS + 1)]
    rows = [
        "| Anonymous RSS (MiB) after edit | " + " | ".join(f"{point:,}" for point in points) + " |",
        "|---|" + "---|" * len(points),
    ]
    for method, report in reports.items():
        rows.append(f"| {method} | " + " | ".join(f"{report.rss_at(p) / 2**20:.1f}" for p in points) + " |")
    return rows


def tests_part(profile: str, workers: int) -> list[str]:
    """The fuzz and fault tables, measured."""
    records, summary, seconds = run_tests(profile, workers)
    return [
        f"Measured by `python -m pipeline.benchmarks.fault_figures --part tests --profile {profile}` "
        f"({len(METHODS)} methods; pytest: {summary} in {seconds:.0f} s).",
        "",
        *fuzz_table(records),
        "",
        *fault_table(records),
    ]


def sessions_part(reports: dict[str, SessionReport], edits: int) -> list[str]:
    """The long-session tables of `reports`."""
    return [
        f"Measured by `python -m pipeline.benchmarks.fault_figures --part sessions --edits {edits}` (one "
        f"process, the methods one after another, one torch thread; tiny caches of 16 x 12 pixels).",
        "",
        *session_table(reports, edits),
        "",
        *curve_table(reports, edits),
    ]


def replace_section(document: str, part: str, lines: list[str]) -> str | None:
    """`document` with the text between `part`'s markers replaced by `lines` (None: no markers)."""
    start, end = MARKERS[part]
    if start not in document or end not in document:
        return None
    before, rest = document.split(start, 1)
    return before + "\n".join([start, "", *lines, "", end]) + rest.split(end, 1)[1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=("all", *MARKERS), default="all", help="what to measure (default all)")
    parser.add_argument("--profile", default="nightly", help="hypothesis profile: default or nightly")
    parser.add_argument("--workers", type=int, default=2, help="pytest-xdist workers (default 2)")
    parser.add_argument("--edits", type=int, default=10_000, help="long-session edits per method")
    parser.add_argument("--write", type=Path, help="Markdown file whose figure sections are replaced")
    parser.add_argument("--curve", type=Path, help="CSV of the long sessions' memory curve")
    args = parser.parse_args(argv)
    parts: dict[str, list[str]] = {}
    if args.part in ("all", "tests"):
        parts["tests"] = tests_part(args.profile, args.workers)
    if args.part in ("all", "sessions"):
        torch.set_num_threads(1)
        reports = run_sessions(args.edits)
        parts["sessions"] = sessions_part(reports, args.edits)
        if args.curve:
            write_text_atomic(args.curve, curve_csv(reports))
    for lines in parts.values():
        print("\n".join(lines) + "\n")
    if args.write:
        document = args.write.read_text()
        for part, lines in parts.items():
            replaced = replace_section(document, part, lines)
            if replaced is None:
                print(f"{args.write}: no {' ... '.join(MARKERS[part])} section to replace", file=sys.stderr)
                return 2
            document = replaced
        write_text_atomic(args.write, document)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
