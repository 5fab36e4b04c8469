"""Helpers of the fuzz and fault tests (tests/test_fuzz_*.py, tests/test_faults*.py).

Run as a script, `python fuzz_support.py FSIZE -- relight arguments...` runs `relight` in this
process with every file it writes limited to FSIZE bytes (RLIMIT_FSIZE; SIGXFSZ ignored, so a
write past the limit fails with EFBIG as on a full disk) — 0 for no limit.

Tiny bakes of the bundled Cornell box for every method (16 x 12, small settings), copies of
them to damage, the `relight render` outcome of a (possibly damaged) cache as a value, and the
hypothesis profiles: 'default' keeps the suite fast on two cores, 'nightly' (selected with
HYPOTHESIS_PROFILE=nightly) runs many more examples.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, settings

from pipeline import cli
from pipeline.bake.inputs import CODE_VERSION_VARIABLE
from pipeline.benchmarks.tiny_caches import METHODS, SCENE, bake_arguments, bake_tiny, quiet_main  # noqa: F401
from relight_torch.io.exr import read_exr

RENDER_SECONDS = 60
"""An open + render of a tiny cache that takes longer than this counts as a hang."""

_health = [HealthCheck.too_slow, HealthCheck.function_scoped_fixture, HealthCheck.data_too_large]
settings.register_profile("default", max_examples=6, deadline=None, derandomize=True, suppress_health_check=_health)
settings.register_profile("nightly", max_examples=300, deadline=None, suppress_health_check=_health)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))


def bake_all(directory: Path, methods: tuple[str, ...] = METHODS) -> dict[str, Path]:
    """`bake_tiny` (method -> cache layer), as a test fixture wants it."""
    return bake_tiny(directory, methods)


def copy_cache(layer: Path, directory: Path) -> Path:
    """Copy a cache and its shot into `directory` (same relative layout); the copy's layer."""
    root = layer.parent.parent
    shutil.copytree(root / "scene", directory / "scene", dirs_exist_ok=True)
    shutil.copytree(layer.parent, directory / layer.parent.name)
    return directory / layer.parent.name / layer.name


@contextlib.contextmanager
def bounded(seconds: float):
    """Raise TimeoutError in this (main) thread when the block runs longer than `seconds`."""

    def expire(signum, frame):
        raise TimeoutError(f"still running after {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


@dataclass(frozen=True)
class Outcome:
    """What `relight render` made of a cache: refused with one line, or rendered."""

    status: int
    error: str
    image: np.ndarray | None
    seconds: float


def render(layer: Path, out: Path, *options: str) -> Outcome:
    """`relight render LAYER -o OUT OPTIONS` in this process, bounded in time.

    Any exception other than the CLI's own exit (a traceback) propagates: it is what the fuzz
    tests look for.
    """
    start = time.perf_counter()
    with bounded(RENDER_SECONDS):
        status, stderr = quiet_main(["render", str(layer), "-o", str(out), *options])
    seconds = time.perf_counter() - start
    errors = [line for line in stderr.splitlines() if line.startswith("relight: error: ")]
    image = None
    if status != 0:
        assert not list(out.parent.glob(f"{out.stem}*")), f"a refused render left {out} behind"
    else:
        frames = sorted(out.parent.glob(f"{out.stem}*.exr"))
        assert frames, f"render exited 0 without writing {out}"
        image = np.stack([np.stack(list(read_exr(f)[0].values()), -1) for f in frames])
    return Outcome(status, errors[-1] if errors else "", image, seconds)


def assert_refused_or_finite(outcome: Outcome, *names: str | Path) -> None:
    """Exit 2 with exactly one `relight: error:` line naming one of `names`, or exit 0 with finite pixels."""
    if outcome.status == 0:
        assert outcome.image is not None and np.isfinite(outcome.image).all(), "rendered non-finite pixels"
        return
    assert outcome.status == 2, outcome
    assert outcome.error and "\n" not in outcome.error, outcome
    assert any(str(name) in outcome.error for name in names), (outcome.error, names)


def tree_hash(directory: Path) -> str:
    """sha256 over the relative names and bytes of every file under `directory` (sorted)."""
    digest = hashlib.sha256()
    for path in sorted(p for p in directory.rglob("*") if p.is_file()):
        digest.update(f"{path.relative_to(directory)}\0".encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def npy_header_span(path: Path) -> int:
    """Bytes of a .npy file's magic, length and header (the data starts there)."""
    data = path.read_bytes()
    length = int.from_bytes(data[8:10], "little") if data[6] == 1 else int.from_bytes(data[8:12], "little")
    return (10 if data[6] == 1 else 12) + length


def payload_files(layer: Path) -> list[Path]:
    """The payload files a cache layer names (from its text: the reader is under test)."""
    names = re.findall(r"asset relight:file = @\./([^@]+)@", layer.read_text())
    return [layer.parent / name for name in names]


TALLY_VARIABLE = "RELIGHT_FAULT_TALLY"
"""When set, a file the fuzz and fault tests append one JSON line per example to (what was tried
and how it ended), for `pipeline.benchmarks.fault_figures`."""


def tally(test: str, **record) -> None:
    """Append {"test": test, **record} to the tally file, if one is set (one short O_APPEND write,
    so xdist workers do not interleave lines)."""
    path = os.environ.get(TALLY_VARIABLE)
    if path:
        line = json.dumps({"test": test, **record}) + "\n"
        descriptor = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(descriptor, line.encode())
        finally:
            os.close(descriptor)


def relight_process(
    arguments: list[str], file_size_limit: int = 0, code_version: str = "test-faults"
) -> subprocess.Popen:
    """`relight ARGUMENTS` in a child process (one torch thread, a pinned code version), started."""
    environment = {
        **os.environ,
        "OMP_NUM_THREADS": "1",
        CODE_VERSION_VARIABLE: code_version,
        "PYTHONPATH": os.pathsep.join(filter(None, [str(Path(__file__).parent.parent), os.environ.get("PYTHONPATH")])),
    }
    return subprocess.Popen(
        [sys.executable, __file__, str(file_size_limit), "--", *arguments],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env=environment,
    )


def run_relight(arguments: list[str], file_size_limit: int = 0, timeout: float = 300) -> tuple[int, str]:
    """`relight_process` run to its end -> (exit status, stderr)."""
    process = relight_process(arguments, file_size_limit)
    _, stderr = process.communicate(timeout=timeout)
    return process.returncode, stderr


if __name__ == "__main__":
    import resource

    limit = int(sys.argv[1])
    if limit:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    sys.exit(cli.main(sys.argv[3:]))
