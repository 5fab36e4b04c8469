"""Distribution: a bake on a Dask cluster (two worker processes on loopback) writes the same cache
as the local bake, byte for byte (every chunk is deterministic)."""

from __future__ import annotations

import filecmp

import distributed

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
