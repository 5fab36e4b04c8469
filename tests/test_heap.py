"""`pipeline.heap.use_one_heap_arena`: threads started after it share glibc's arenas instead of
taking one each (the relighter's worker threads then reuse each other's freed temporaries)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

SCRIPT = """
import ctypes, sys, threading
if sys.argv[1] == "one":
    from pipeline.heap import use_one_heap_arena
    assert use_one_heap_arena()
barrier = threading.Barrier(8)
def work():
    buffers = [ctypes.create_string_buffer(4096) for _ in range(64)]  # malloc'd while all 8 are alive
    barrier.wait()
threads = [threading.Thread(target=work) for _ in range(8)]
for thread in threads:
    thread.start()
for thread in threads:
    thread.join()
ctypes.CDLL(None).malloc_stats()
"""


def arenas(mode: str) -> int:
    """The number of glibc arenas after 8 threads allocate at once, in a fresh interpreter."""
    environment = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    environment.pop("MALLOC_ARENA_MAX", None)
    result = subprocess.run(
        [sys.executable, "-c", SCRIPT, mode], capture_output=True, text=True, check=True, env=environment
    )
    return sum(line.startswith("Arena ") for line in result.stderr.splitlines())


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc_stats")
def test_threads_share_one_arena():
    default, one = arenas("default"), arenas("one")
    assert default >= 4  # glibc gave most of the threads an arena of their own
    assert one < default and one <= 2  # the main thread's (and one an import may have made)
