"""A re-bake that fails leaves the previous cache as it was: bakes run in a staging folder, then commit.

`relight bake --out DIR` bakes into `DIR/.<stem>.staging/` (the method's payloads, its layer and
its resumable chunk folders, `pipeline.bake.scheduler`), and only a finished bake is committed
into DIR. Until then DIR's old cache (layer and payloads) is untouched, so a bake that dies of a
full disk, a bad input or a bug leaves it usable; a killed one leaves it too, and its re-run
resumes from the chunks kept in the staging folder.

The commit is renames within one file system, then the layer: the old layer is removed first,
the new payloads renamed over the old ones, the new layer written last (atomically), then the old
cache's payloads the new one does not name are deleted. A reader meanwhile sees the old cache, no
layer, or the new cache (a payload no longer matching the layer it read is refused by its
sha256), never a mix. The layer is re-authored rather than renamed because it records the shot
and the input files relative to its own folder.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

from pipeline.errors import RelightError
from relight_torch.cache.layer import read_cache_layer, write_cache_layer


def staging_folder(out_dir: Path, stem: str) -> Path:
    """Where a bake of `stem` into `out_dir` writes until it is committed."""
    return out_dir / f".{stem}.staging"


@contextlib.contextmanager
def staged_bake(out_dir: str | os.PathLike[str], stem: str) -> Iterator[Path]:
    """Yield the staging folder to bake `stem` into; the caller then calls `commit_staged`.

    On an exception the staging folder loses its finished files (payloads and layer of the failed
    bake) but keeps its hidden chunk folders, to resume from; an empty staging folder, and an
    output folder this call created and left empty, are removed.
    """
    out_dir = Path(out_dir)
    created = not out_dir.exists()
    staging = staging_folder(out_dir, stem)
    try:
        yield staging
    except BaseException:
        _discard_failed(staging, out_dir if created else None)
        raise


def commit_staged(staged_layer: Path, out_dir: str | os.PathLike[str]) -> Path:
    """Move a finished staged cache into `out_dir` (see the module doc); the committed layer's path.

    Raises:
        RelightError: a rename or the layer's write failed (one line naming the file): DIR then
            holds no cache layer (its old one was removed first), never a mix.
    """
    out_dir = Path(out_dir)
    staging = staged_layer.parent
    description = read_cache_layer(staged_layer)
    target = out_dir / staged_layer.name
    old_files = _payload_files(target)
    target.unlink(missing_ok=True)
    for payload in description.payloads:
        try:
            os.replace(staging / payload.file, out_dir / payload.file)
        except OSError as error:
            raise RelightError(
                f"{out_dir / payload.file}: could not be committed ({error.strerror or error})"
            ) from None
    _fsync_directory(out_dir)
    write_cache_layer(target, description)
    for name in old_files - {payload.file for payload in description.payloads}:
        (out_dir / name).unlink(missing_ok=True)
    shutil.rmtree(staging, ignore_errors=True)
    return target


def _payload_files(layer: Path) -> set[str]:
    """The payload file names an existing cache layer names (none when it is missing or unreadable)."""
    try:
        return {payload.file for payload in read_cache_layer(layer).payloads} if layer.is_file() else set()
    except RelightError:
        return set()


def _discard_failed(staging: Path, created_out: Path | None) -> None:
    """Remove a failed bake's finished files from `staging` (its hidden chunk folders stay)."""
    if staging.is_dir():
        for path in staging.iterdir():
            if not path.name.startswith(".") and path.is_file():
                path.unlink(missing_ok=True)
        with contextlib.suppress(OSError):
            staging.rmdir()  # only when empty: no chunks to resume from
    if created_out is not None:
        with contextlib.suppress(OSError):
            created_out.rmdir()


def _fsync_directory(directory: Path) -> None:
    """Make the renames in `directory` durable before the layer that names their files is written."""
    descriptor = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)
