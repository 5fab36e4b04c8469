"""Read-only arrays over memory-mapped files, and giving their pages back.

A mapped page that has been read counts in the process's resident set (and in its peak) until
the mapping goes, even though the kernel could drop it. A large array that is read once and then
kept for rare use (the occluder triangles, copied into Embree's own buffers) is mapped with
`map_array` and its pages released with `release_pages` after each block is read: its resident
cost is then one block, not the file.
"""

from __future__ import annotations

import mmap
from typing import BinaryIO

import numpy as np
from numpy.lib.array_utils import byte_bounds


def map_array(
    handle: BinaryIO, shape: tuple[int, ...], dtype: np.dtype, offset: int, fortran_order: bool
) -> np.ndarray:
    """A read-only array of `shape` and `dtype` over an open file's bytes from `offset` (no copy).

    The array keeps the mapping alive (its `base`); the file handle may be closed afterwards.
    """
    mapping = mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ)
    return np.ndarray(shape, dtype, buffer=mapping, offset=offset, order="F" if fortran_order else "C")


def _mapping(array: np.ndarray) -> mmap.mmap | None:
    """The mmap an array's memory belongs to (through its chain of bases), or None."""
    base: object = array
    while base is not None and not isinstance(base, mmap.mmap):
        base = getattr(base, "base", None)
    return base


def release_pages(array: np.ndarray) -> None:
    """Drop from the resident set the mapped pages that hold `array`'s bytes (an array or view made
    by `map_array`); a later read maps them again from the page cache. Arrays that are not
    file-mapped are left alone."""
    mapping = _mapping(array)
    if mapping is None or array.size == 0:
        return
    origin = np.frombuffer(mapping, np.uint8, 0).__array_interface__["data"][0]
    low, high = byte_bounds(array)
    # Whole pages around the array's bytes: a read-only shared mapping loses nothing by dropping more.
    first = (low - origin) // mmap.PAGESIZE * mmap.PAGESIZE
    mapping.madvise(mmap.MADV_DONTNEED, first, min(len(mapping), high - origin) - first)
