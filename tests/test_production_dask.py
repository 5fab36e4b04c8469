"""Distribution: a bake on a Dask cluster (two worker processes on loopback) writes the same cache
as the local bake, byte for byte (every chunk is deterministic), also when a worker is killed in
the middle of a chunk (the scheduler runs the lost chunk again elsewhere)."""

from __future__ import annotations

import filecmp
import os
from pathlib import Path

import distributed
import pytest

import production_support
from pipeline.cli import main


def test_dask_bake_equals_the_local_bake(tmp_path, monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # inherited by the workers: one thread per task
    shot = production_support.write_shot(tmp_path / "scene")
    local, remote = tmp_path / "local" / "out", tmp_path / "dask" / "out"  # same depth: same relative paths
    assert main(production_support.bake_arguments(shot, local)) == 0
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None, protocol="tcp"
    ) as cluster:
        assert cluster.scheduler_address.startswith("tcp://127.0.0.1:")
        with distributed.Client(cluster) as client:
            with distributed.get_task_stream(client) as tasks:  # collected when the block ends
                arguments = [*production_support.bake_arguments(shot, remote), "--scheduler", cluster.scheduler_address]
                assert main(arguments) == 0
            chunk_tasks = [task for task in tasks.data if str(task["key"]).startswith("run_chunk")]
            cluster_workers = set(client.scheduler_info()["workers"])
    # The three chunks (deep framebuffer, final gather, bounce) ran on the cluster's workers.
    assert len(chunk_tasks) == 3 and {task["worker"] for task in chunk_tasks} <= cluster_workers
    names = sorted(p.name for p in local.iterdir())
    assert names == sorted(p.name for p in remote.iterdir())
    assert [n for n in names if not filecmp.cmp(local / n, remote / n, shallow=False)] == []


def test_a_worker_killed_mid_chunk_still_gives_the_local_bake(tmp_path, monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    # The workers import the kill hook from this folder (spawned processes inherit the environment).
    tests = str(Path(production_support.__file__).parent)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [tests, os.environ.get("PYTHONPATH")])))
    shot = production_support.write_shot(tmp_path / "scene")
    local, remote = tmp_path / "local" / "out", tmp_path / "dask" / "out"
    assert main(production_support.bake_arguments(shot, local)) == 0
    marker = tmp_path / "killed-worker.pid"
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None, protocol="tcp"
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        before = client.run(os.getpid)
        client.run(production_support.die_inside_the_first_chunk, str(marker))
        arguments = [*production_support.bake_arguments(shot, remote), "--scheduler", cluster.scheduler_address]
        assert main(arguments) == 0
    killed = int(marker.read_text())
    assert killed in before.values()
    with pytest.raises(ProcessLookupError):  # it died (the nanny started another worker)
        os.kill(killed, 0)
    names = sorted(p.name for p in local.iterdir())
    assert names == sorted(p.name for p in remote.iterdir())
    assert [n for n in names if not filecmp.cmp(local / n, remote / n, shallow=False)] == []
