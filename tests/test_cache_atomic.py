"""A bake that fails midway leaves nothing half-written: no temp files, no layer naming a missing payload.

Each writer is made to fail after writing part of its file (disk full, Ctrl-C), at each stage of
`bake_direct`: the EXR payload, the .npy payload, the layer itself. A failed re-bake over an
existing cache may replace payloads under the old layer; the loader must then refuse it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenEXR
import pytest
from pxr import Sdf

import cache_support
from cache_support import bake_bundled
from pipeline.errors import RelightError
from relight_torch.cache.layer import SUFFIX, is_cache_layer, read_cache_layer
from relight_torch.direct.relighter import open_relighter


class _PartialWriteFailure(Exception):
    """Raised by the sabotaged writers after writing some bytes."""


def _write_part_then_fail(path):
    Path(path).write_bytes(b"partial contents")
    raise _PartialWriteFailure("disk full")


class _FailingExrFile:
    """Stands in for OpenEXR.File: writes a few bytes, then fails."""

    def __init__(self, *args, **kwargs):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def write(self, path):
        _write_part_then_fail(path)


def _fail_npy(handle, array, allow_pickle=False):
    handle.write(b"\x93NUMPY partial")
    raise KeyboardInterrupt  # as if the user pressed Ctrl-C: not an Exception, cleanup must still run


_EXPORT = Sdf.Layer.Export


def _fail_cache_layer_export(layer, path, *args, **kwargs):
    """Sdf.Layer.Export, failing for the cache layer only (the bundled scene is written with it too)."""
    if ".relight." not in Path(path).name:
        return _EXPORT(layer, path, *args, **kwargs)
    _write_part_then_fail(path)


SABOTAGE = {
    "exr": (OpenEXR, "File", _FailingExrFile, _PartialWriteFailure),
    "npy": (np, "save", _fail_npy, KeyboardInterrupt),
    "layer": (Sdf.Layer, "Export", _fail_cache_layer_export, _PartialWriteFailure),
}


def _assert_nothing_half_written(directory: Path) -> None:
    """No temp files (a bake's hidden chunk folders stay, to resume from, with whole chunks only);
    every cache layer present names payloads that exist."""
    assert [p.name for p in directory.rglob(".*") if p.is_file()] == []
    for layer in directory.glob(f"*{SUFFIX}"):
        assert is_cache_layer(layer)
        for payload in read_cache_layer(layer).payloads:
            assert (directory / payload.file).is_file(), payload.file


@pytest.mark.parametrize("writer", SABOTAGE)
def test_failed_bake_leaves_no_temp_files_and_no_layer(writer, tmp_path, monkeypatch):
    owner, name, replacement, raised = SABOTAGE[writer]
    monkeypatch.setattr(owner, name, replacement)
    with pytest.raises(raised):
        bake_bundled("cornell_box", tmp_path)
    cache_dir = tmp_path / "cache"
    _assert_nothing_half_written(cache_dir)
    # The layer is written last, so no failure leaves one.
    assert list(cache_dir.glob(f"*{SUFFIX}")) == []


@pytest.mark.parametrize("writer", ["npy", "layer"])
def test_failed_rebake_over_a_cache_is_refused_not_used(writer, tmp_path, monkeypatch):
    layer = bake_bundled("cornell_box", tmp_path)
    owner, name, replacement, raised = SABOTAGE[writer]
    monkeypatch.setattr(cache_support, "SIZE", 16)
    monkeypatch.setattr(owner, name, replacement)
    with pytest.raises(raised):
        bake_bundled("cornell_box", tmp_path)
    monkeypatch.undo()
    _assert_nothing_half_written(layer.parent)
    # The re-bake removed the old layer before replacing its payloads, so no layer can describe
    # payloads from another bake.
    with pytest.raises(RelightError, match="no such cache layer"):
        open_relighter(layer)
