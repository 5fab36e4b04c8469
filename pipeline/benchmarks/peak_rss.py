"""This process's resident memory, and a runner that reports a Python module's peak.

    python -m pipeline.benchmarks.peak_rss MODULE [ARGS...]

runs MODULE as `python -m MODULE ARGS...` would, in this process, and prints `peak_rss_gb: X` to
stderr when it ends (however it ends). A child's `ru_maxrss` from `wait4` is no measure of the child
alone: Linux keeps the larger of it and the parent's resident set at the spawn (a benchmark that
has imported torch holds half a gigabyte). VmHWM is the high-water mark of the memory the process
has mapped since its exec.
"""

from __future__ import annotations

import os
import runpy
import sys


def _status_kilobytes(field: str) -> int:
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith(f"{field}:"))


def peak_rss_bytes() -> int:
    """This process's peak resident set size since its exec (Linux VmHWM)."""
    return _status_kilobytes("VmHWM") * 1024


def rss_bytes() -> int:
    """This process's resident set size now (Linux: /proc/self/statm's resident pages)."""
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def main() -> None:
    if len(sys.argv) < 2:
        raise SystemExit("usage: python -m pipeline.benchmarks.peak_rss MODULE [ARGS...]")
    module = sys.argv[1]
    sys.argv = sys.argv[1:]
    try:
        runpy.run_module(module, run_name="__main__", alter_sys=True)
    finally:
        print(f"peak_rss_gb: {peak_rss_bytes() / 1e9:.4f}", file=sys.stderr, flush=True)


if __name__ == "__main__":
    main()
