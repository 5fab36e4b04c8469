"""EXR images in and out, with the project's channel conventions (DESIGN.md "Caches").

Beauty is un-prefixed R, G, B (A); layers are `layer.channel` (`albedo.R`, `P.X`, `N.X`, `Z`);
ids are UINT. ZIP compression, never lossy codecs. Writes are atomic.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import OpenEXR
import OpenImageIO as oiio

from relight_torch.errors import RelightError
from relight_torch.io.atomic import atomic_path

OpenEXR.set_global_thread_count(os.cpu_count() or 1)

_ALLOWED = (np.float16, np.float32, np.uint32)
# OpenImageIO's names of the three EXR pixel types, and the numpy dtype each reads back as.
_PIXEL_TYPES: dict[str, np.dtype[Any]] = {
    "half": np.dtype(np.float16),
    "float": np.dtype(np.float32),
    "uint": np.dtype(np.uint32),
}
# The EXR specification's names of the pixel types, by numpy dtype (for messages and reports).
PIXEL_TYPE_NAMES = {np.dtype(np.float16): "HALF", np.dtype(np.float32): "FLOAT", np.dtype(np.uint32): "UINT"}


@dataclass(frozen=True)
class ExrHeader:
    """What an EXR's header says, read without decoding pixels.

    Attributes:
        width, height: data window size in pixels.
        channels: channel name -> numpy dtype of its pixels (float16 HALF, float32 FLOAT, uint32 UINT).
        compression: the codec's name ('zip', 'piz', 'dwaa', ...).
    """

    width: int
    height: int
    channels: dict[str, np.dtype]
    compression: str


def write_exr(
    path: str | os.PathLike[str], channels: dict[str, np.ndarray], attributes: dict[str, object] | None = None
) -> None:
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
    with atomic_path(path) as temp, OpenEXR.File(header, data) as exr:
        try:
            exr.write(str(temp))
        except RuntimeError as error:  # OpenEXR's failed write (disk full...): atomic_path reports OSErrors
            raise OSError(_one_line(error)) from error


def write_rgb_exr(
    path: str | os.PathLike[str],
    rgb: np.ndarray,
    layers: dict[str, np.ndarray] | None = None,
    attributes: dict[str, object] | None = None,
) -> None:
    """Write an (H, W, 3) float image as R, G, B (float32), plus optional `layer` -> (H, W, 3) as layer.R/G/B."""
    channels = {c: rgb[..., i].astype(np.float32) for i, c in enumerate("RGB")}
    for layer, image in (layers or {}).items():
        for i, c in enumerate("RGB"):
            channels[f"{layer}.{c}"] = image[..., i].astype(np.float32)
    write_exr(path, channels, attributes)


def exr_layer_names(names: list[str], taken: tuple[str, ...] = ()) -> list[str]:
    """EXR layer names for arbitrary names (light groups...), one each, distinct.

    A layer name may not hold '.' (the layer separator); to keep names portable to compositing
    tools, every character other than ASCII letters, digits, '_' and '-' becomes '_'. Names that
    collide after that (or with `taken`) get '_2', '_3'... appended.
    """
    used, layers = set(taken), []
    for name in names:
        base = re.sub(r"[^A-Za-z0-9_-]", "_", name) or "_"
        layer, suffix = base, 1
        while layer in used:
            suffix += 1
            layer = f"{base}_{suffix}"
        used.add(layer)
        layers.append(layer)
    return layers


def _one_line(text: str | BaseException) -> str:
    """The last non-empty line of a (possibly multi-line) library message: its most specific part."""
    lines = [line.strip() for line in str(text).splitlines() if line.strip()]
    return lines[-1] if lines else "unknown error"


def _oiio_error() -> str:
    """OpenImageIO's last error, one line; its text can hold a damaged header's bytes, which are not
    always UTF-8 (the binding then raises UnicodeDecodeError instead of returning it)."""
    try:
        return _one_line(oiio.geterror())
    except UnicodeDecodeError:
        return "the header holds bytes that are not UTF-8 text"


def read_exr_header(path: str | os.PathLike[str]) -> ExrHeader:
    """Read part 0's header: size, channel names and pixel types, compression.

    OpenImageIO reads it: OpenEXR's Python header-only mode does not report pixel types.

    Raises:
        RelightError: the file is missing or its header is not a readable EXR header.
    """
    path = Path(path)
    if not path.is_file():
        raise RelightError(f"{path}: no such EXR file")
    image = oiio.ImageInput.open(str(path))
    if image is None:
        raise RelightError(f"{path}: not a readable EXR file ({_oiio_error()})")
    try:
        spec = image.spec()
        if image.format_name() != "openexr":
            raise RelightError(f"{path}: is a {image.format_name()} image, not an EXR file")
        formats = spec.channelformats or [spec.format] * spec.nchannels
        unknown = sorted({str(f) for f in formats} - set(_PIXEL_TYPES))
        if unknown:
            raise RelightError(f"{path}: unsupported EXR pixel type {unknown[0]}")
        channels = {name: _PIXEL_TYPES[str(f)] for name, f in zip(spec.channelnames, formats, strict=True)}
        return ExrHeader(
            width=spec.width,
            height=spec.height,
            channels=channels,
            compression=str(spec.getattribute("compression") or "none"),
        )
    finally:
        image.close()


def read_exr(path: str | os.PathLike[str]) -> tuple[dict[str, np.ndarray], dict[str, object]]:
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
        raise RelightError(f"{path}: not a readable EXR file ({_one_line(error)})") from None
    return channels, header


def read_rgb_exr(path: str | os.PathLike[str], layer: str = "") -> np.ndarray:
    """Read (H, W, 3) float32 from R, G, B (or `layer`.R/G/B)."""
    channels, _ = read_exr(path)
    prefix = f"{layer}." if layer else ""
    names = [f"{prefix}{c}" for c in "RGB"]
    missing = [n for n in names if n not in channels]
    if missing:
        raise RelightError(f"{path}: missing channels {', '.join(missing)}")
    return np.stack([channels[n].astype(np.float32) for n in names], axis=-1)
