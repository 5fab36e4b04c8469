"""Coarse-grained CPU parallelism: the independent pieces of one stage on a few Python threads.

torch parallelises each operation over its intra-op threads (OpenMP). The direct relighter's
light transport is a chain of ~1,000 operations on 10^5-element tensors, many of which run on
one thread or pay a fork and join per call. Tiles of shading points share no state and run on
threads of their own, each with one intra-op thread (torch and Embree release the GIL in their
kernels): a transfer light move at 640 x 480 on 2 idle cores went from 106 to 98 ms median
(155 to 147 ms with F per pixel), A/B in one process. Smaller stages (the surface filter, the F
product, the gathers' light) measured slower split than under OpenMP and are not split. The bakers and the reference
renderer parallelise the same way (`torch_threads(1)` around a thread pool).

The workers live as long as the process: a thread's first torch operation costs ~2 ms of
set-up, which a pool made per call paid every time (4 ms per call against 0.25 ms).
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

import torch

T = TypeVar("T")
R = TypeVar("R")

_worker = threading.local()
_pool: ThreadPoolExecutor | None = None
_pool_lock = threading.Lock()


@contextlib.contextmanager
def torch_threads(num_threads: int) -> Iterator[None]:
    """Run the block with torch's intra-op thread count set to `num_threads`, then restore it.

    Threads started inside the block take this count when they first run a parallel torch op.
    """
    previous = torch.get_num_threads()
    torch.set_num_threads(num_threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def in_worker() -> bool:
    """Whether the calling thread is one of `parallel_map`'s workers (which do not fan out again)."""
    return getattr(_worker, "active", False)


def _mark_worker() -> None:
    _worker.active = True


def tile_threads(device: torch.device, thread_safe: bool = True) -> int:
    """Threads for the pieces of a stage on `device`: torch's intra-op thread count on the CPU,
    1 on a GPU (which parallelises each operation), inside a worker, or for work whose calls
    must not overlap (`thread_safe` False)."""
    if device.type != "cpu" or not thread_safe or in_worker():
        return 1
    return torch.get_num_threads()


def parallel_map(function: Callable[[T], R], items: Sequence[T], num_threads: int) -> list[R]:
    """[function(item) for item in items], the items spread over `num_threads` threads.

    `function` must be thread-safe; it runs torch with one intra-op thread. With one thread or one
    item, or from inside a worker, the items run in turn on the calling thread. Returns the
    results in the order of `items`; the first exception raised by a piece is re-raised.
    """
    num_threads = min(len(items), num_threads)
    if num_threads <= 1 or in_worker():
        return [function(item) for item in items]
    with torch_threads(1):  # a worker's first torch operation fixes its thread count at 1
        return list(_workers(num_threads).map(function, items))


def _workers(num_threads: int) -> ThreadPoolExecutor:
    """The process's worker pool, grown to at least `num_threads` threads."""
    global _pool
    with _pool_lock:
        if _pool is None or _pool._max_workers < num_threads:
            if _pool is not None:
                _pool.shutdown(wait=False)
            _pool = ThreadPoolExecutor(num_threads, thread_name_prefix="relight", initializer=_mark_worker)
        return _pool
