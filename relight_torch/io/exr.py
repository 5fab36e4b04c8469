"""EXR images in and out, with the project's channel conventions (DESIGN.md "Caches").

Beauty is un-prefixed R, G, B (A); layers are `layer.channel` (`albedo.R`, `P.X`, `N.X`, `Z`);
ids are UINT. ZIP compression, never lossy codecs. Writes are atomic.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import OpenEXR

from relight_torch.io.atomic import atomic_path
from relight_torch.errors import RelightError

OpenEXR.set_global_thread_count(os.cpu_count() or 1)

_ALLOWED = (np.float16, np.float32, np.uint32)


def write_exr(path: str | os.PathLike, channels: dict[str, np.ndarray],
              attributes: dict[str, object] | None = None) -> None:
    """Write single-part scanline EXR with ZIP compression, atomically.

    Args:
        path: output file.
        channels: name -> (H, W) array of float16, float32 or uint32 (all the same H, W).
        attributes: extra header attributes (str, int, float values).
    """
    if not channels:
        raise ValueError("write_exr needs at least one channel")
    shapes = {name: array.shape for name, array in channels.items()}
    if len(set(shapes.values())) != 1 or len(next(iter(shapes.values()))) != 2:
        raise ValueError(f"EXR channels must share one (H, W) shape, got {shapes}")
    data = {}
    for name, array in channels.items():
        if array.dtype.type not in _ALLOWED:
            raise ValueError(f"EXR channel {name!r} has dtype {array.dtype}; use float16, float32 or uint32")
        data[name] = np.ascontiguousarray(array)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    header.update(attributes or {})
    with atomic_path(path) as temp:
        with OpenEXR.File(header, data) as exr:
            exr.write(str(temp))


def write_rgb_exr(path: str | os.PathLike, rgb: np.ndarray,
                  layers: dict[str, np.ndarray] | None = None,
                  attributes: dict[str, object] | None = None) -> None:
    """Write an (H, W, 3) float image as R, G, B (float32), plus optional `layer` -> (H, W, 3) as layer.R/G/B."""
    channels = {c: rgb[..., i].astype(np.float32) for i, c in enumerate("RGB")}
    for layer, image in (layers or {}).items():
        for i, c in enumerate("RGB"):
            channels[f"{layer}.{c}"] = image[..., i].astype(np.float32)
    write_exr(path, channels, attributes)


def read_exr(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict[str, object]]:
    """Read every channel of part 0 as separate (H, W) arrays, and the header.

    Raises:
        RelightError: the file is missing or not a readable EXR.
    """
    path = Path(path)
    if not path.is_file():
        raise RelightError(f"{path}: no such EXR file")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            part = exr.parts[0]
            channels = {name: np.array(ch.pixels) for name, ch in part.channels.items()}
            header = dict(part.header)
    except Exception as error:  # OpenEXR raises plain Exceptions for corrupt files
        raise RelightError(f"{path}: not a readable EXR file ({error})") from error
    return channels, header


def read_rgb_exr(path: str | os.PathLike, layer: str = "") -> np.ndarray:
    """Read (H, W, 3) float32 from R, G, B (or `layer`.R/G/B)."""
    channels, _ = read_exr(path)
    prefix = f"{layer}." if layer else ""
    names = [f"{prefix}{c}" for c in "RGB"]
    missing = [n for n in names if n not in channels]
    if missing:
        raise RelightError(f"{path}: missing channels {', '.join(missing)}")
    return np.stack([channels[n].astype(np.float32) for n in names], axis=-1)
