"""The chunk scheduler: valid chunks are kept, anything else is recomputed; stale bakes say what changed."""

from __future__ import annotations

import dataclasses
import logging
import os
import types
from pathlib import Path

import numpy as np
import pytest

import production_support
import sky_support
from pipeline import progress
from pipeline.bake import scheduler
from pipeline.bake.direct.bake import bake_direct
from pipeline.bake.quality import measurement_window, resized
from pipeline.bake.scheduler import ChunkSpec, ShotSpec, chunk_folder, chunk_ranges, load_chunk, run_chunks
from pipeline.bake.transfer import bake as transfer
from pipeline.cli import main
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES
from relight_torch.cache.layer import read_cache_layer
from relight_torch.cache.status import cache_status

SHOT = ShotSpec("/nonexistent/shot.usda", "/Camera", 4, 4)
CALLS: list[tuple[int, int]] = []


def squares(spec: ChunkSpec) -> dict[str, np.ndarray]:
    """A chunk: the squares of its range times parameter 'scale'."""
    CALLS.append((spec.start, spec.stop))
    return {"values": np.arange(spec.start, spec.stop) ** 2 * spec.param("scale")}


def _specs(scale: int = 1) -> list[ChunkSpec]:
    return [
        ChunkSpec(SHOT, "squares", (("scale", scale),), start, stop, (("threads", 1),))
        for start, stop in chunk_ranges(10, 4)
    ]


def test_chunk_ranges_cover_the_work_once():
    assert chunk_ranges(10, 4) == [(0, 4), (4, 8), (8, 10)]
    assert chunk_ranges(0, 4) == [(0, 0)]  # one empty chunk: a camera that sees only sky still joins arrays
    with pytest.raises(ValueError, match="chunk size"):
        chunk_ranges(10, 0)


def test_valid_chunks_are_kept_and_bad_ones_recomputed(tmp_path):
    CALLS.clear()
    paths = run_chunks(squares, _specs(), tmp_path, progress=False)
    assert [p.name for p in paths] == [f"squares-{a:09d}-{b:09d}.npz" for a, b in chunk_ranges(10, 4)]
    assert np.concatenate([load_chunk(p)["values"] for p in paths]).tolist() == [i * i for i in range(10)]
    assert len(CALLS) == 3

    CALLS.clear()
    paths[0].write_bytes(paths[0].read_bytes()[:-20])  # truncated (a hand edit, a bad disk)
    paths[1].write_bytes(paths[2].read_bytes())  # another chunk's file
    (tmp_path / ".squares-000000008-000000010.tmp-1.npz").write_bytes(b"half")  # a killed writer's temp
    speedier = [ChunkSpec(s.shot, s.name, s.parameters, s.start, s.stop, (("threads", 2),)) for s in _specs()]
    again = run_chunks(squares, speedier, tmp_path, progress=False)
    assert sorted(CALLS) == [(0, 4), (4, 8)]  # options are not part of a chunk's identity
    assert np.concatenate([load_chunk(p)["values"] for p in again]).tolist() == [i * i for i in range(10)]
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []

    CALLS.clear()
    run_chunks(squares, _specs(scale=3), tmp_path, progress=False)  # another parameter: nothing reused
    assert len(CALLS) == 3


def test_chunk_folders_of_other_inputs_are_removed(tmp_path):
    old = chunk_folder(tmp_path, "shot", "direct", "a" * 64)
    old.mkdir()
    other_stem = chunk_folder(tmp_path, "other", "direct", "a" * 64)
    other_stem.mkdir()
    new = chunk_folder(tmp_path, "shot", "direct", "b" * 64)
    assert new.name == ".shot.direct-" + "b" * 16
    assert not old.exists() and other_stem.exists()


def test_dask_address_without_a_cluster_is_one_clear_error(tmp_path):
    with scheduler.using(scheduler.Scheduler(address="dask")), pytest.raises(Exception, match="scheduler-address"):
        run_chunks(squares, _specs(), tmp_path, progress=False)


def _bake(shot: Path, out: Path) -> Path:
    scene = load_scene(shot, width=8, height=8)
    return bake_direct(scene, find_camera(scene, SCENES["cornell_box"].camera), out, "cornell_box", 1, 1)


def test_changed_input_is_reported_stale_and_baked_afresh(tmp_path, capsys):
    shot = production_support.write_shot(tmp_path / "scene")
    layer = _bake(shot, tmp_path / "cache")
    description = read_cache_layer(layer)
    assert description.code_version and len(description.content_hash) == 64
    assert main(["info", str(layer)]) == 0
    out = capsys.readouterr().out
    assert f"  code version: {description.code_version}" in out and "  status: valid" in out

    with open(shot, "a") as handle:
        handle.write("\n# an artist's edit\n")
    assert cache_status(layer).stale_inputs == {str(shot.resolve()): "changed"}
    assert main(["info", str(layer)]) == 1
    out = capsys.readouterr().out
    assert "  status: stale" in out and f"input {shot.resolve()} changed since the bake" in out
    rebaked = read_cache_layer(_bake(shot, tmp_path / "cache"))
    assert rebaked.content_hash != description.content_hash and cache_status(layer).verdict == "valid"


def worker_pid(spec: ChunkSpec) -> dict[str, np.ndarray]:
    """A chunk: its squares and the id of the process that computed it."""
    return {**squares(spec), "pid": np.array(os.getpid())}


def test_a_local_pool_computes_the_chunks_in_worker_processes(tmp_path):
    with scheduler.using(scheduler.Scheduler(workers=2)):
        paths = run_chunks(worker_pid, _specs(), tmp_path, progress=False)
    chunks = [load_chunk(p) for p in paths]
    assert os.getpid() not in {int(c["pid"]) for c in chunks}
    assert np.concatenate([c["values"] for c in chunks]).tolist() == [i * i for i in range(10)]


def test_transfer_rows_are_the_same_on_one_or_two_threads_and_resume(tmp_path, monkeypatch):
    """Replaces the closure-based check of `bake_rows` (tests/test_transfer.py) on the chunk API."""
    shot_path = production_support.write_shot(tmp_path / "scene")
    scene = load_scene(shot_path, width=8, height=8)
    shot = ShotSpec.of(scene, find_camera(scene, SCENES["cornell_box"].camera))
    baked = {}
    for threads in (1, 2):
        settings = transfer.TransferSettings(
            num_gathers=16, rows_per_chunk=16, pairs_per_batch=5 * 16, num_threads=threads
        )
        baked[threads] = transfer.bake_rows(
            shot, transfer.F_PREFIX, 37, 6, 1, settings, tmp_path / str(threads), progress=False
        ).arrays()
    assert baked[1].keys() == baked[2].keys()
    for name in baked[1]:
        np.testing.assert_array_equal(baked[1][name], baked[2][name])
    # Run again: every chunk is on disk, nothing is evaluated.
    monkeypatch.setattr(transfer, "final_gather_rows", lambda *args: pytest.fail("a finished chunk was re-evaluated"))
    again = transfer.bake_rows(shot, transfer.F_PREFIX, 37, 6, 1, settings, tmp_path / "2", progress=False).arrays()
    np.testing.assert_array_equal(again["Values"], baked[2]["Values"])


@pytest.mark.parametrize("view", ["window", "reduced", "pilot"])
def test_a_process_reading_a_view_of_the_shot_reads_the_drivers_surfaces_and_camera(tmp_path, view):
    """Pool and Dask workers read the shot again from its spec. A measurement window, a reduced
    view of indirect rows and a pilot are views of the shot as the driver read it: the worker must
    refine the subdivision teapots for the shot's size (not the view's: a 160x120 window of a
    640x480 read had given a quarter of the triangles, so other gathers) and see the window's film."""
    shot = sky_support.write_exterior_shot(tmp_path, 1, 1)
    scene = load_scene(shot, width=160, height=120)
    camera = find_camera(scene, "/Shot/Cams/Horizon")
    driver_scene, driver_camera = {
        "window": lambda: measurement_window(scene, camera, 40 * 32),
        "reduced": lambda: transfer.reduced_view(scene, camera, 2),
        "pilot": lambda: resized(scene, camera, 64, 48),
    }[view]()
    spec = ShotSpec.of(driver_scene, driver_camera)
    scheduler._REMEMBERED.clear()  # as in a worker process
    worker_scene, worker_camera = scheduler.load_shot(spec)
    assert worker_scene is not driver_scene
    np.testing.assert_array_equal(worker_scene.geometry.positions, driver_scene.geometry.positions)
    for name in (field.name for field in dataclasses.fields(driver_camera)):
        np.testing.assert_array_equal(getattr(worker_camera, name), getattr(driver_camera, name), err_msg=name)


def test_work_without_a_bar_logs_its_progress_once_a_minute(monkeypatch, caplog):
    """A bake whose stderr is a log file says how far it is: one line a minute, none after the end."""
    clock = iter([0.0, 0.0, 30.0, 61.0, 90.0, 125.0, 200.0])
    monkeypatch.setattr(progress, "time", types.SimpleNamespace(monotonic=lambda: next(clock)))
    caplog.set_level(logging.INFO, logger=progress.__name__)
    with progress.progress_bar("transfer rows", 100, "rows", enabled=False) as update:
        for done in (10, 20, 30, 40, 60, 100):  # resumed: 10 were baked before
            update(done, 100)
    lines = [record.getMessage() for record in caplog.records]
    assert lines == [
        "transfer rows: 30 of 100 rows (30%), 61 s elapsed, about 4 min left",
        "transfer rows: 60 of 100 rows (60%), 2 min elapsed, about 2 min left",
    ]
