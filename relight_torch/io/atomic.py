"""Atomic file writes: write beside the target, fsync, then rename over it.

A reader (or a re-run after SIGKILL) sees either the old file or the complete new one, never a
half-written one. Temp files are named `.<name>.tmp-<pid>` in the target's directory, so the
rename never crosses a filesystem.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

from relight_torch.errors import RelightError


@contextlib.contextmanager
def atomic_path(target: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path to write; on success it replaces `target`, on error it is removed.

    Raises:
        RelightError: an OSError while writing or renaming (disk full...), naming `target`.

    The temporary name keeps the target's suffix, so format-sniffing writers (OpenEXR, USD,
    OpenImageIO) pick the right format.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    temp = target.with_name(f".{target.stem}.tmp-{os.getpid()}{target.suffix}")
    try:
        yield temp
        with open(temp, "rb+") as handle:
            os.fsync(handle.fileno())
        os.replace(temp, target)
    except OSError as error:  # disk full, quota, permissions: one line naming the file
        raise RelightError(
            f"{target}: could not be written ({error.strerror or error}); nothing was replaced"
        ) from error
    finally:
        with contextlib.suppress(FileNotFoundError):
            temp.unlink()


def remove_temp_files(directory: str | os.PathLike[str], stem: str = "") -> list[Path]:
    """Delete the temp files `atomic_path` left in `directory` for targets named `<stem>...` (all
    with stem ''): a process killed while writing (SIGKILL, power loss) never removes its own.
    Call it only where no other live writer is at work; returns what was removed."""
    removed = []
    for temp in Path(directory).glob(f".{stem}*.tmp-*"):
        if temp.is_file():
            temp.unlink(missing_ok=True)
            removed.append(temp)
    return removed


def write_bytes_atomic(target: str | os.PathLike[str], data: bytes) -> None:
    """Write `data` to `target` atomically."""
    with atomic_path(target) as temp:
        temp.write_bytes(data)


def write_text_atomic(target: str | os.PathLike[str], text: str) -> None:
    """Write `text` (UTF-8) to `target` atomically."""
    write_bytes_atomic(target, text.encode("utf-8"))
