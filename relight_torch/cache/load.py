"""Loading a cache safely: everything is checked before anything big is allocated.

Order: the layer parses and names a supported version (`layer.read_cache_layer`); then, per
payload, the file exists, its header (EXR data window, channel names and pixel types; .npy shape
and dtype) matches what the layer records, and its size and sha256 match (streamed, so a corrupt
or truncated file is refused without being loaded); then the inputs the bake read are re-hashed,
so a cache whose shot changed is reported stale, naming the files. The header comes before the
hash so that a payload replaced by another file says what is wrong with it (another resolution,
other channels), not only that its bytes changed. A payload is checked and decoded through one open
handle (`opened_payload`), so a file renamed over it meanwhile (a re-bake) is never decoded against
the old record. No pickle anywhere: .npy headers are parsed here with `ast.literal_eval` and the
arrays mapped read-only (`relight_torch.io.mapped`: their pages can be given back once read).
"""

from __future__ import annotations

import ast
import contextlib
import hashlib
import math
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from relight_torch.cache.gbuffer_exr import check_channel_types, gbuffer_from_channels
from relight_torch.cache.layer import CacheDescription, Payload, file_sha256, plain_dtype
from relight_torch.errors import RelightError
from relight_torch.gbuffer import GBuffer
from relight_torch.io.exr import ExrHeader, read_exr, read_exr_header
from relight_torch.io.mapped import map_array

MAX_EXR_EXPANSION = 2048
"""An EXR payload whose header claims more raw pixel bytes than this many times its file size is
refused before it is read: no compression OpenEXR writes for us (ZIP deflate tops out near 1032:1)
gets there, so only a forged header does, and reading it would allocate what it claims."""


def payload_file(layer_path: Path, payload: Payload) -> Path:
    """The payload's file beside the layer (resolved), which must exist."""
    path = (Path(layer_path).parent / payload.file).resolve()
    if not path.is_file():
        raise RelightError(f"{layer_path}: payload {payload.name} file {path} is missing")
    return path


def _handle_sha256(handle: BinaryIO) -> str:
    """Hex sha256 of an open file's bytes, read from its start in 1 MB blocks."""
    handle.seek(0)
    digest = hashlib.sha256()
    for block in iter(lambda: handle.read(1 << 20), b""):
        digest.update(block)
    return digest.hexdigest()


def check_payload_bytes(path: Path, payload: Payload, handle: BinaryIO | None = None) -> None:
    """Refuse a payload file whose size or sha256 differs from the layer's record.

    Args:
        handle: the file open in binary mode, to check that very file (else `path` is opened).
    """
    if handle is None:
        with open(path, "rb") as own:
            return check_payload_bytes(path, payload, own)
    size = os.fstat(handle.fileno()).st_size
    if size < payload.num_bytes:
        raise RelightError(f"{path}: payload {payload.name} is truncated ({size} of {payload.num_bytes} bytes)")
    if size != payload.num_bytes:
        raise RelightError(
            f"{path}: payload {payload.name} is {size} bytes, the cache layer records "
            f"{payload.num_bytes} (replaced or appended to)"
        )
    if _handle_sha256(handle) != payload.sha256:
        raise RelightError(
            f"{path}: payload {payload.name} does not match the sha256 the cache layer records "
            f"(corrupt, edited, or overwritten by another bake)"
        )
    return None


def sub_sample_size(description: CacheDescription) -> tuple[int, int]:
    """(H, W) of the cache's EXR payloads: the resolution times the supersampling."""
    width, height = description.resolution
    return height * description.supersampling, width * description.supersampling


def _exr_image_size(payload: Payload, description: CacheDescription) -> tuple[int, int]:
    """(H, W) of an EXR payload: its recorded shape, else the cache's sub-sample size."""
    if not payload.shape:
        return sub_sample_size(description)
    height, width = payload.shape  # empty or (H, W): `read_cache_layer` refuses any other EXR shape
    return height, width


def check_exr_header(path: Path, payload: Payload, header: ExrHeader, image_size: tuple[int, int]) -> None:
    """Refuse an EXR payload whose size, channel names or pixel types differ from the layer's.

    Args:
        header: the file's header (`read_exr_header`).
        image_size: the expected (H, W).
    """
    height, width = image_size
    raw = header.width * header.height * sum(dtype.itemsize for dtype in header.channels.values())
    if raw > MAX_EXR_EXPANSION * path.stat().st_size:
        raise RelightError(
            f"{path}: payload {payload.name} header claims {header.width}x{header.height} x "
            f"{len(header.channels)} channels ({raw} bytes) from a {path.stat().st_size}-byte file; "
            f"refused before reading"
        )
    if (header.height, header.width) != (height, width):
        raise RelightError(
            f"{path}: payload {payload.name} is a {header.width}x{header.height} EXR, "
            f"the cache layer says {width}x{height}"
        )
    if set(header.channels) != set(payload.channels):
        extra = sorted(set(header.channels) - set(payload.channels))
        missing = sorted(set(payload.channels) - set(header.channels))
        raise RelightError(
            f"{path}: payload {payload.name} channels differ from the cache layer's "
            f"(unexpected {extra}, missing {missing})"
        )
    check_channel_types(header.channels, str(path))


NPY_MAGIC = b"\x93NUMPY"
MAX_NPY_HEADER = 10_000
"""Longest .npy header read (numpy's own default limit): ours are under 200 bytes."""
_NPY_KEYS = {"descr", "fortran_order", "shape"}

NpyHeader = tuple[tuple[int, ...], np.dtype[Any], bool, int]
"""(shape, dtype, fortran_order, data offset) of a .npy file (`read_npy_header`)."""


def _npy_header_dict(handle: BinaryIO, path: Path) -> dict[str, Any]:
    """The header dictionary of an open .npy file, its handle left at the first data byte.

    Parsed here, not by numpy's reader: that one runs Python's tokenizer over the header and lets
    its errors (`tokenize.TokenError`, `SyntaxError`, `RecursionError`...) escape on damaged bytes.
    """
    magic = handle.read(8)
    if len(magic) < 8 or magic[:6] != NPY_MAGIC:
        raise RelightError(f"{path}: not a .npy array (no .npy magic string)")
    version = (magic[6], magic[7])
    if version not in ((1, 0), (2, 0)):
        raise RelightError(f"{path}: not a .npy array (unsupported .npy version {version[0]}.{version[1]})")
    length_bytes = handle.read(2 if version == (1, 0) else 4)
    length = int.from_bytes(length_bytes, "little")
    if len(length_bytes) < (2 if version == (1, 0) else 4) or not 1 <= length <= MAX_NPY_HEADER:
        raise RelightError(f"{path}: not a .npy array (header length {length} is not in 1..{MAX_NPY_HEADER})")
    text = handle.read(length)
    if len(text) < length:
        raise RelightError(f"{path}: not a .npy array (header cut short at {len(text)} of {length} bytes)")
    try:
        header = ast.literal_eval(text.decode("latin1"))
    except (ValueError, TypeError, SyntaxError, MemoryError, RecursionError) as error:
        reason = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise RelightError(f"{path}: not a .npy array (malformed header: {reason})") from None
    if not isinstance(header, dict) or set(header) != _NPY_KEYS:
        raise RelightError(f"{path}: not a .npy array (the header is not a dictionary of {sorted(_NPY_KEYS)})")
    return header


def read_npy_header(path: Path, handle: BinaryIO | None = None) -> NpyHeader:
    """(shape, dtype, fortran_order, data offset) from a .npy file's header, without reading the array.

    Args:
        path: the file (named in errors).
        handle: the file already open in binary mode (read from its start), else `path` is opened.

    Raises:
        RelightError: not a .npy file, an unsupported version, a malformed header, a dtype holding
            objects or of zero size, or a header whose shape and dtype do not account for the file's
            size exactly (a header claiming a huge array is refused before anything is allocated or
            mapped).
    """
    if handle is None:
        with open(path, "rb") as own:
            return read_npy_header(path, own)
    handle.seek(0)
    header = _npy_header_dict(handle, path)
    data_offset = handle.tell()
    shape, descr, fortran_order = header["shape"], header["descr"], header["fortran_order"]
    if not isinstance(shape, tuple) or not all(type(n) is int and n >= 0 for n in shape):
        raise RelightError(f"{path}: not a .npy array (shape {shape!r} is not a tuple of counts)")
    if not isinstance(fortran_order, bool):
        raise RelightError(f"{path}: not a .npy array (fortran_order {fortran_order!r} is not a bool)")
    if not isinstance(descr, str) or not plain_dtype(descr):
        raise RelightError(f"{path}: not a .npy array (descr {descr!r} is not a plain numpy dtype)")
    dtype = np.dtype(descr)
    if dtype.itemsize == 0:
        raise RelightError(f"{path}: not a .npy array (dtype {descr!r} has no size)")
    data_bytes = math.prod(shape) * dtype.itemsize
    size = os.fstat(handle.fileno()).st_size
    if data_offset + data_bytes != size:
        raise RelightError(
            f"{path}: .npy header claims {dtype.name}{list(shape)} ({data_bytes} bytes of data) but "
            f"the file holds {size - data_offset}; refused before reading"
        )
    return shape, dtype, fortran_order, data_offset


def check_npy_header(path: Path, payload: Payload, header: NpyHeader) -> None:
    """Refuse a .npy payload whose shape or dtype (`header`, from `read_npy_header`) differ from the layer's."""
    shape, dtype = header[:2]
    if shape != payload.shape or dtype.name != payload.dtype:
        raise RelightError(
            f"{path}: payload {payload.name} is {dtype.name}{list(shape)}, the cache layer says "
            f"{payload.dtype}{list(payload.shape)}"
        )


@contextlib.contextmanager
def opened_payload(
    layer_path: Path, description: CacheDescription, payload: Payload, image_size: tuple[int, int] | None = None
) -> Iterator[tuple[Path, BinaryIO, ExrHeader | NpyHeader]]:
    """Open one payload file and make every check short of decoding it; yields (path, handle, header).

    The header and bytes checked are those of the open handle's file, so what is decoded from the
    handle (`load_npy` maps it) is what was checked, even if a re-bake renames a new file over the
    path meanwhile. A header that cannot be parsed in a file shorter than recorded is reported as
    truncated; a header that parses but differs from the layer's record is reported as such,
    whatever the size.

    Args:
        image_size: an EXR payload's expected (H, W) (default: the layer's shape, else the cache's
            sub-sample size).

    Raises:
        RelightError: one line naming the file and what is wrong with it.
    """
    path = payload_file(layer_path, payload)
    with contextlib.ExitStack() as stack:
        try:
            handle = stack.enter_context(open(path, "rb"))
        except OSError as error:
            raise RelightError(f"{path}: payload {payload.name} cannot be opened ({error.strerror})") from None
        try:
            header: ExrHeader | NpyHeader = (
                read_exr_header(path) if payload.format == "exr" else read_npy_header(path, handle)
            )
        except RelightError:
            if os.fstat(handle.fileno()).st_size < payload.num_bytes:
                check_payload_bytes(path, payload, handle)
            raise
        if isinstance(header, ExrHeader):
            check_exr_header(path, payload, header, image_size or _exr_image_size(payload, description))
        else:
            check_npy_header(path, payload, header)
        check_payload_bytes(path, payload, handle)
        yield path, handle, header


def check_payload(layer_path: Path, description: CacheDescription, payload: Payload) -> Path:
    """Every check of one payload file short of decoding it (`opened_payload`); returns its path."""
    with opened_payload(layer_path, description, payload) as (path, _, _):
        return path


def _identity(status: os.stat_result) -> tuple[int, ...]:
    return status.st_dev, status.st_ino, status.st_size, status.st_mtime_ns, status.st_ctime_ns


def read_payload_exr(
    layer_path: Path, description: CacheDescription, payload: Payload, image_size: tuple[int, int] | None = None
) -> tuple[Path, dict[str, np.ndarray]]:
    """An EXR payload's channels, checked as `opened_payload` does; returns (path, channels).

    OpenEXR reads by path, so the file is checked to be the one whose bytes were hashed after it is
    decoded (the handle held open meanwhile, so its inode cannot be reused).

    Raises:
        RelightError: as `opened_payload`, or the file was replaced while being read.
    """
    with opened_payload(layer_path, description, payload, image_size) as (path, handle, _):
        channels, _ = read_exr(path)
        replaced = not path.is_file() or _identity(os.stat(path)) != _identity(os.fstat(handle.fileno()))
    if replaced:
        raise RelightError(
            f"{path}: payload {payload.name} was replaced while being read (a bake writing "
            f"this cache?); open the cache again"
        )
    return path, channels


def stale_inputs(description: CacheDescription) -> dict[str, str]:
    """Input file -> 'missing' or 'changed', for every input the bake read that is not as it was."""
    stale = {}
    for file, digest in sorted(description.inputs.items()):
        if not os.path.isfile(file):
            stale[file] = "missing"
        elif file_sha256(file) != digest:
            stale[file] = "changed"
    return stale


def check_inputs(layer_path: Path, description: CacheDescription) -> None:
    """Refuse a stale cache: an input the bake read is missing or changed since (all are named)."""
    stale = stale_inputs(description)
    if stale:
        what = ", ".join(f"{file} {state}" for file, state in stale.items())
        raise RelightError(f"{layer_path}: stale cache: input {what} since the bake; re-bake it")


def load_gbuffer(layer_path: Path, description: CacheDescription) -> GBuffer:
    """The deep framebuffer payload as a CPU GBuffer."""
    payload = description.payload("deepFramebuffer")
    path, channels = read_payload_exr(layer_path, description, payload)
    camera_position = description.world_from_camera[:3, 3]
    return gbuffer_from_channels(channels, payload.constants, camera_position, str(path))


def load_npy(layer_path: Path, description: CacheDescription, name: str) -> np.ndarray:
    """A .npy payload, memory-mapped read-only from the very file whose header and bytes were checked.

    An empty array is returned as such (there is nothing to map).
    """
    payload = description.payload(name)
    with opened_payload(layer_path, description, payload) as (path, handle, header):
        if isinstance(header, ExrHeader):
            raise RelightError(f"{path}: payload {name} is an EXR image, not a .npy array")
        shape, dtype, fortran_order, offset = header
        if math.prod(shape) == 0:
            return np.empty(shape, dtype, order="F" if fortran_order else "C")
        return map_array(handle, shape, dtype, offset, fortran_order)
