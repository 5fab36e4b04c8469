"""Real faults: a full disk during `relight bake` and `relight render`, SIGKILL at random moments of a
bake, and readers rendering while a re-bake replaces the cache.

The disk fills up for real: the child process runs with RLIMIT_FSIZE (SIGXFSZ ignored), so the
write that crosses the limit fails with EFBIG inside OpenEXR, numpy or USD, as on a full file
system. Kills are real SIGKILLs from outside at random times during the bake. The default suite
runs the disk-full bake for two methods and one kill point for two others; HYPOTHESIS_PROFILE=nightly
runs every method, KILLS_NIGHTLY kill points each.
"""

from __future__ import annotations

import filecmp
import os
import random
import shutil
import signal
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from fuzz_support import (
    METHODS,
    SCENE,
    bake_arguments,
    quiet_main,
    relight_process,
    render,
    run_relight,
    tally,
    tree_hash,
)
from pipeline.bake.inputs import CODE_VERSION_VARIABLE
from pipeline.scenes import SCENES
from relight_torch.cache.status import cache_status

NIGHTLY = os.environ.get("HYPOTHESIS_PROFILE") == "nightly"
KILLS_NIGHTLY = 20
CODE_VERSION = "test-faults"


@pytest.fixture(scope="module")
def shot(tmp_path_factory) -> Path:
    return SCENES[SCENE].write(tmp_path_factory.mktemp("faults") / "scene")


@pytest.fixture(scope="module")
def clean(shot) -> dict[str, tuple[Path, str, float]]:
    """Each method's uninterrupted bake, in this process: method -> (cache folder, tree hash, seconds)."""
    previous = os.environ.get(CODE_VERSION_VARIABLE)
    os.environ[CODE_VERSION_VARIABLE] = CODE_VERSION
    try:
        bakes = {}
        for method in METHODS:
            out = shot.parent.parent / "clean" / method
            start = time.perf_counter()
            status, stderr = quiet_main(bake_arguments(shot, out, method))
            assert status == 0, stderr
            bakes[method] = (out, tree_hash(out), time.perf_counter() - start)
        return bakes
    finally:
        os.environ.pop(CODE_VERSION_VARIABLE) if previous is None else os.environ.update(
            {CODE_VERSION_VARIABLE: previous}
        )


def _beside_clean(shot: Path, tmp_path: Path, method: str) -> Path:
    """An output folder at the clean bakes' depth beside the shared shot: the layer records the same
    relative and absolute input paths, so an equal bake is byte-equal."""
    return shot.parent.parent / tmp_path.name / method


def _one_error_line(stderr: str) -> str:
    lines = [line for line in stderr.splitlines() if line.startswith("relight: error: ")]
    assert len(lines) == 1 and "Traceback" not in stderr, stderr
    return lines[0]


def _leftovers(out: Path) -> list[Path]:
    """Temp files of atomic writes, and cache layers, under `out`."""
    return sorted(p for p in out.rglob("*") if ".tmp-" in p.name or p.name.endswith(".relight.usda"))


@pytest.mark.slow
@pytest.mark.parametrize("method", METHODS if NIGHTLY else ("transfer", "multiview"))
def test_disk_full_during_a_bake_leaves_no_cache_and_a_rerun_bakes_the_same(shot, clean, tmp_path, method):
    out = _beside_clean(shot, tmp_path, method)
    arguments = bake_arguments(shot, out, method)
    clean_out, clean_hash, _ = clean[method]
    largest = max(p.stat().st_size for p in clean_out.iterdir())
    limit = random.Random(method).randrange(largest // 8, largest)
    status, stderr = run_relight(arguments, file_size_limit=limit)
    assert status == 2, stderr
    line = _one_error_line(stderr)
    # 'File too large' (EFBIG) from most writers; numpy's tofile says '... requested and ... written'.
    assert str(out) in line and "could not be written" in line and "nothing was replaced" in line, line
    assert not _leftovers(out), _leftovers(out)
    # Space freed: the re-run finishes (from the chunks already done) with the clean bake's files.
    status, stderr = run_relight(arguments)
    assert status == 0, stderr
    assert tree_hash(out) == clean_hash
    tally("disk full during a bake", method=method, refused=True)


@pytest.mark.slow
@pytest.mark.parametrize("method", METHODS if NIGHTLY else ("transfer",))
def test_a_failed_rebake_leaves_the_old_cache_usable(shot, clean, tmp_path, method):
    """A re-bake (another resolution) into the folder of a good cache fails midway on a full disk:
    the old cache is untouched (same files, valid) and renders the same image."""
    out = _beside_clean(shot, tmp_path, method)
    shutil.copytree(clean[method][0], out)
    layer = out / f"{SCENE}.relight.usda"
    before = render(layer, tmp_path / "before.exr").image
    arguments = [*bake_arguments(shot, out, method), "--width", "8", "--height", "6"]  # the last --width wins
    status, stderr = run_relight(arguments, file_size_limit=2048)
    assert status == 2 and "could not be written" in _one_error_line(stderr), stderr
    # Before bakes ran in a staging folder, the failed re-bake had already removed the old layer.
    visible = sorted(p.name for p in clean[method][0].iterdir())
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == visible
    assert all(filecmp.cmp(clean[method][0] / name, out / name, shallow=False) for name in visible)
    assert cache_status(layer).verdict == "valid"
    assert np.array_equal(render(layer, tmp_path / "after.exr").image, before)
    # Space freed: the re-bake resumes from its chunks and replaces the cache.
    status, stderr = run_relight(arguments)
    assert status == 0, stderr
    assert render(layer, tmp_path / "new.exr").image.shape[1:3] == (6, 8)
    assert sorted(p.name for p in out.iterdir()) == visible  # no staging folder, no payload of the old cache
    tally("failed re-bake over a cache", method=method, refused=True)


@pytest.mark.parametrize("method", METHODS if NIGHTLY else ("multiview",))
def test_disk_full_during_a_render_writes_nothing(clean, tmp_path, method):
    layer = clean[method][0] / f"{SCENE}.relight.usda"
    image = tmp_path / "relit.exr"
    status, stderr = run_relight(
        ["render", str(layer), "-o", str(image), "--png", str(tmp_path / "relit.png")], file_size_limit=512
    )
    assert status == 2, stderr
    line = _one_error_line(stderr)
    assert str(tmp_path) in line and "could not be written" in line, line
    assert not list(tmp_path.iterdir())
    assert cache_status(layer).verdict == "valid"
    tally("disk full during a render", method=method, refused=True)


def _kill_points(method: str) -> list[float]:
    """Fractions of a bake's running time (after its output folder appears) to SIGKILL it at."""
    rng = random.Random(f"kill-{method}")
    return [rng.random() for _ in range(KILLS_NIGHTLY if NIGHTLY else 1)]


def _bake_killed_at(arguments: list[str], out: Path, seconds: float) -> tuple[int, float]:
    """Start the bake and SIGKILL it `seconds` after `out` appears, unless it ends first.

    Returns:
        Its exit status (-SIGKILL when killed) and how long it ran after `out` appeared.
    """
    process = relight_process(arguments)
    while not out.exists() and process.poll() is None:
        time.sleep(0.002)
    start = time.perf_counter()
    try:
        process.wait(timeout=seconds)
    except subprocess.TimeoutExpired:
        process.send_signal(signal.SIGKILL)
        process.wait()
    process.stderr.close()
    return process.returncode, time.perf_counter() - start


@pytest.mark.slow
@pytest.mark.parametrize("method", METHODS if NIGHTLY else ("gather", "cuts"))
def test_bake_killed_at_random_moments_resumes_to_the_uninterrupted_cache(shot, clean, tmp_path, method):
    out = _beside_clean(shot, tmp_path, method)
    arguments = bake_arguments(shot, out, method)
    duration = clean[method][2]  # an in-process bake: what a child runs once its output folder exists
    landed = 0
    for fraction in _kill_points(method):
        status, _ = _bake_killed_at(arguments, out, fraction * duration)
        assert status in (0, -signal.SIGKILL)
        landed += status == -signal.SIGKILL
    status, stderr = run_relight(arguments)
    assert status == 0, stderr
    assert tree_hash(out) == clean[method][1]
    tally("SIGKILL during a bake", method=method, kills=len(_kill_points(method)), landed=landed)


def test_readers_during_a_rebake_see_the_old_or_the_new_cache(shot, clean, tmp_path):
    """Renders of a cache while a re-bake (another resolution) replaces it: each is the old image, the
    new one, or a one-line refusal (the cache is mid-replacement on disk); never a mix."""
    out = _beside_clean(shot, tmp_path, "direct")
    old_arguments = bake_arguments(shot, out, "direct")
    new_arguments = [*old_arguments, "--width", "8", "--height", "6"]  # the last --width wins
    layer = out / f"{SCENE}.relight.usda"
    images = {}
    for name, arguments in (("new", new_arguments), ("old", old_arguments)):
        status, stderr = quiet_main(arguments)
        assert status == 0, stderr
        images[name] = render(layer, tmp_path / f"{name}.exr").image
    assert not np.array_equal(images["old"], images["new"])
    seen, stop = [], threading.Event()

    def rebake() -> None:
        for arguments in (new_arguments, old_arguments):
            status, stderr = run_relight(arguments)
            assert status == 0, stderr
        stop.set()

    writer = threading.Thread(target=rebake)
    writer.start()
    try:
        while not stop.is_set():
            outcome = render(layer, tmp_path / "reader" / "relit.exr")
            if outcome.status == 0:
                matches = [name for name, image in images.items() if np.array_equal(outcome.image, image)]
                assert matches, "a reader rendered neither the old nor the new cache"
                seen.append(matches[0])
                shutil.rmtree(tmp_path / "reader")
            else:
                assert outcome.status == 2 and outcome.error, outcome
                seen.append("refused")
    finally:
        writer.join()
    assert seen
    tally("readers during a re-bake", method="direct", **{name: seen.count(name) for name in ("old", "new", "refused")})
