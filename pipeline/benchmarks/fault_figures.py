"""The figures of docs/ERRORS.md's 'Fuzzed and faulted' section, measured by running what they describe.

    python -m pipeline.benchmarks.fault_figures --profile nightly --edits 10000 --write docs/ERRORS.md

runs the fuzz and fault tests (tests/test_fuzz_caches.py, test_fuzz_stages.py, test_faults.py)
under the hypothesis profile, each example appending what it tried and how it ended to a tally
file (tests/fuzz_support.py, RELIGHT_FAULT_TALLY); then the long session of
`pipeline.benchmarks.long_session` with EDITS edits per method. It prints the tables and, with
--write, replaces the text between the section's markers in that file.
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

from pipeline.benchmarks.long_session import SessionReport, curve_csv, run_sessions
from pipeline.benchmarks.tiny_caches import METHODS
from relight_torch.io.atomic import write_text_atomic

FUZZ_TESTS = ("damaged cache", "bad lights layer", "bad shot")
"""The tallies (tests/fuzz_support.py `tally`) of generated inputs; the rest are faults."""
TESTS = ("tests/test_fuzz_caches.py", "tests/test_fuzz_stages.py", "tests/test_faults.py")
START, END = "<!-- fault-figures:start -->", "<!-- fault-figures:end -->"
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


def session_table(reports: dict[str, SessionReport], edits: int) -> list[str]:
    """Markdown rows of the long sessions."""
    rows = [
        "| Method | Edits | RSS at start | RSS at end | Growth after the first 10 % | Largest checkpoint difference |",
        "|---|---|---|---|---|---|",
    ]
    for method, report in reports.items():
        rows.append(
            f"| {method} | {edits} | {report.rss[0][1] / 2**20:.1f} MiB | "
            f"{report.rss[-1][1] / 2**20:.1f} MiB | {100 * report.growth_after(0.1):+.2f} % | "
            f"{max(report.checkpoint_errors):.1e} |"
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--profile", default="nightly", help="hypothesis profile: default or nightly")
    parser.add_argument("--workers", type=int, default=2, help="pytest-xdist workers (default 2)")
    parser.add_argument("--edits", type=int, default=10_000, help="long-session edits per method")
    parser.add_argument("--write", type=Path, help="Markdown file whose fault-figures section is replaced")
    parser.add_argument("--curve", type=Path, help="CSV of the long sessions' memory curve")
    args = parser.parse_args(argv)
    records, summary, seconds = run_tests(args.profile, args.workers)
    reports = run_sessions(args.edits)
    sessions = session_table(reports, args.edits)
    lines = [
        START,
        "",
        f"Measured by `python -m pipeline.benchmarks.fault_figures --profile {args.profile} --edits {args.edits}` "
        f"({len(METHODS)} methods; pytest: {summary} in {seconds:.0f} s).",
        "",
        *fuzz_table(records),
        "",
        *fault_table(records),
        "",
        *sessions,
        "",
        END,
    ]
    text = "\n".join(lines)
    print(text)
    if args.curve:
        write_text_atomic(args.curve, curve_csv(reports))
    if args.write:
        document = args.write.read_text()
        if START not in document or END not in document:
            print(f"{args.write}: no {START} ... {END} section to replace", file=sys.stderr)
            return 2
        before, rest = document.split(START, 1)
        write_text_atomic(args.write, before + text + rest.split(END, 1)[1])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
