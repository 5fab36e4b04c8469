"""Nothing lost: a bake SIGKILLed at several points and run again ends with the cache of an
uninterrupted bake, recomputing only the chunks that were not finished."""

from __future__ import annotations

import filecmp
import os
import signal
import subprocess
import sys
from pathlib import Path

import production_support
from pipeline.bake.inputs import CODE_VERSION_VARIABLE
from pipeline.cli import main
from relight_torch.cache.status import cache_status

HELPER = Path(production_support.__file__)
CODE_VERSION = "test-resume"


def _bake_killed_at(kill_at: str, arguments: list[str]) -> subprocess.CompletedProcess:
    # One pinned code version for all runs: the source digest would follow edits made meanwhile.
    environment = {**os.environ, "OMP_NUM_THREADS": "1", CODE_VERSION_VARIABLE: CODE_VERSION}
    return subprocess.run(
        [sys.executable, str(HELPER), kill_at, "--", *arguments],
        capture_output=True,
        text=True,
        env=environment,
        timeout=300,
    )


def _chunks(directory: Path) -> list[Path]:
    return [p for p in directory.rglob("*.npz") if not p.name.startswith(".")]


def _files(directory: Path) -> list[str]:
    return sorted(str(p.relative_to(directory)) for p in directory.rglob("*"))


def test_bake_killed_at_several_points_resumes_to_the_uninterrupted_cache(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv(CODE_VERSION_VARIABLE, CODE_VERSION)
    shot = production_support.write_shot(tmp_path / "scene")
    clean, killed = tmp_path / "clean" / "out", tmp_path / "killed" / "out"  # same depth: same relative paths
    assert main(production_support.bake_arguments(shot, clean)) == 0
    arguments = production_support.bake_arguments(shot, killed)

    # Killed right after its first chunk (the deep framebuffer).
    first = _bake_killed_at("chunk:1", arguments)
    assert first.returncode == -signal.SIGKILL, first.stderr
    assert len(_chunks(killed)) == 1 and not list(killed.glob("*.relight.usda"))

    # Killed inside its first chunk write (the bounce rows: M is baked before F, whose rows are
    # refitted to the shot's lights carried through M), the temp file not yet renamed.
    second = _bake_killed_at("chunk-write", arguments)
    assert second.returncode == -signal.SIGKILL, second.stderr
    assert "deep framebuffer: 1 of 1 chunks already baked" in second.stderr
    assert len(list(killed.rglob(".bounce*.tmp-*"))) == 1 and len(_chunks(killed)) == 1

    # Killed inside the cache layer's write: finished chunks are not recomputed, a half-written
    # layer is never in place.
    third = _bake_killed_at("layer-write", arguments)
    assert third.returncode == -signal.SIGKILL, third.stderr
    assert "deep framebuffer: 1 of 1 chunks already baked" in third.stderr
    assert not list(killed.glob("*.relight.usda")) and len(list(killed.rglob(".*.relight.tmp-*"))) == 1

    last = _bake_killed_at("none", arguments)
    assert last.returncode == 0, last.stderr
    capsys.readouterr()
    # Same files, byte for byte (the layer too): no temp files or chunk folders left.
    assert _files(killed) == _files(clean)
    assert all(filecmp.cmp(clean / name, killed / name, shallow=False) for name in _files(clean))
    assert cache_status(next(killed.glob("*.relight.usda"))).verdict == "valid"
