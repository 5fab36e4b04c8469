"""Helpers of the fuzz and fault tests (tests/test_fuzz_*.py, tests/test_faults*.py).

Tiny bakes of the bundled Cornell box for every method (16 x 12, small settings), copies of
them to damage, the `relight render` outcome of a (possibly damaged) cache as a value, and the
hypothesis profiles: 'default' keeps the suite fast on two cores, 'nightly' (selected with
HYPOTHESIS_PROFILE=nightly) runs many more examples.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import os
import re
import shutil
import signal
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, settings

from pipeline import cli
from pipeline.scenes import SCENES
from relight_torch.io.exr import read_exr

SCENE = "cornell_box"
WIDTH, HEIGHT = 16, 12
COMMON_OPTIONS = ["--width", str(WIDTH), "--height", str(HEIGHT), "--supersampling", "1", "--texture-samples", "1"]
METHOD_OPTIONS = {
    "direct": [],
    "transfer": ["--gathers", "16", "--coefficients", "8", "--bounces", "2", "--bounce-coefficients", "4"],
    "gather": ["--directions", "16", "--clusters", "4", "--representatives", "32"],
    "cuts": ["--mode", "indirect", "--cut-lights", "16"],
    "multiview": ["--caching-resolution", "16", "--coverage", "0.5"],
}
"""Small settings per method: each bakes in about a second at 16 x 12."""
METHODS = tuple(METHOD_OPTIONS)
RENDER_SECONDS = 60
"""An open + render of a tiny cache that takes longer than this counts as a hang."""

_health = [HealthCheck.too_slow, HealthCheck.function_scoped_fixture, HealthCheck.data_too_large]
settings.register_profile("default", max_examples=6, deadline=None, derandomize=True,
                          suppress_health_check=_health)
settings.register_profile("nightly", max_examples=300, deadline=None, suppress_health_check=_health)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))


def bake_arguments(shot: Path, out: Path, method: str) -> list[str]:
    """`relight bake` arguments of the tiny bake of `method`."""
    return ["bake", str(shot), "--camera", SCENES[SCENE].camera, "--out", str(out), "--method", method,
            *COMMON_OPTIONS, *METHOD_OPTIONS[method]]


def quiet_main(arguments: list[str]) -> tuple[int, str]:
    """`relight ARGUMENTS` in this process -> (exit status, stderr); stdout is discarded."""
    stderr = io.StringIO()
    with contextlib.redirect_stderr(stderr), contextlib.redirect_stdout(io.StringIO()):
        status = cli.main(arguments)
    return status, stderr.getvalue()


def bake_all(directory: Path, methods: tuple[str, ...] = METHODS) -> dict[str, Path]:
    """The shot under directory/scene and one tiny cache per method under directory/<method>.

    Returns:
        method -> cache layer.
    """
    shot = SCENES[SCENE].write(directory / "scene")
    layers = {}
    for method in methods:
        status, stderr = quiet_main(bake_arguments(shot, directory / method, method))
        assert status == 0, stderr
        layers[method] = directory / method / f"{SCENE}.relight.usda"
    return layers


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
