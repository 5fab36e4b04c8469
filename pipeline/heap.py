"""The C heap of a `relight` process: one malloc arena.

glibc gives each thread that allocates while another holds the heap lock an arena of its own (up
to 8 per core). The relighter's worker threads (Embree chunks, tiles of points) free large
temporaries in one arena that the next tile, on another thread, cannot reuse, so the resident set
grows by the arenas' free space. One arena (as `MALLOC_ARENA_MAX=1`) keeps that space shared: on
the 1000-teapot exterior the relighter's peak fell from 3.59 to 3.42 GB at 640x480 and from 8.09
to 7.80 GB at 1920x1080 with a 1 GB budget, the CPU time per light move unchanged within a loaded
machine's noise (`pipeline/benchmarks/relight_memory.py`). The torch and numpy arrays these
threads allocate are large and few, so the one lock is not contended.
"""

from __future__ import annotations

import ctypes

M_ARENA_MAX = -8
"""glibc's mallopt parameter number for the arena limit (malloc.h)."""


def use_one_heap_arena() -> bool:
    """Limit glibc's malloc to one arena for the threads started from now on (call it before any).

    Returns:
        True if the C library took the setting; False where it is not glibc (nothing changes).
    """
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(M_ARENA_MAX, 1))
