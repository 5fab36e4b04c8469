"""Loading a cache safely: everything is checked before anything big is allocated.

Order: the layer parses and names a supported version (`layer.read_cache_layer`); then, per
payload, the file exists, its header (EXR data window, channel names and pixel types; .npy shape
and dtype) matches what the layer records, and its size and sha256 match (streamed, so a corrupt
or truncated file is refused without being loaded); then the inputs the bake read are re-hashed,
so a cache whose shot changed is reported stale, naming the files. The header comes before the
hash so that a payload replaced by another file says what is wrong with it (another resolution,
other channels), not only that its bytes changed. No pickle anywhere: .npy files are read with
allow_pickle=False.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from relight_torch.cache.gbuffer_exr import check_channel_types, gbuffer_from_channels
from relight_torch.cache.layer import CacheDescription, Payload, file_sha256
from relight_torch.errors import RelightError
from relight_torch.gbuffer import GBuffer
from relight_torch.io.exr import ExrHeader, read_exr, read_exr_header


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


def check_payload_bytes(path: Path, payload: Payload) -> None:
    """Refuse a payload file whose size or sha256 differs from the layer's record."""
    size = path.stat().st_size
    if size < payload.num_bytes:
        raise RelightError(f"{path}: payload {payload.name} is truncated ({size} of {payload.num_bytes} bytes)")
    if size != payload.num_bytes:
        raise RelightError(f"{path}: payload {payload.name} is {size} bytes, the cache layer records "
                           f"{payload.num_bytes} (replaced or appended to)")
    if file_sha256(path) != payload.sha256:
        raise RelightError(f"{path}: payload {payload.name} does not match the sha256 the cache layer records "
                           f"(corrupt, edited, or overwritten by another bake)")


def sub_sample_size(description: CacheDescription) -> tuple[int, int]:
    """(H, W) of the cache's EXR payloads: the resolution times the supersampling."""
    width, height = description.resolution
    return height * description.supersampling, width * description.supersampling


def check_exr_header(path: Path, payload: Payload, header: ExrHeader, image_size: tuple[int, int]) -> None:
    """Refuse an EXR payload whose size, channel names or pixel types differ from the layer's.

    Args:
        header: the file's header (`read_exr_header`).
        image_size: the expected (H, W).
    """
    height, width = image_size
    raw = header.width * header.height * sum(dtype.itemsize for dtype in header.channels.values())
    if raw > MAX_EXR_EXPANSION * path.stat().st_size:
        raise RelightError(f"{path}: payload {payload.name} header claims {header.width}x{header.height} x "
                           f"{len(header.channels)} channels ({raw} bytes) from a {path.stat().st_size}-byte file; "
                           f"refused before reading")
    if (header.height, header.width) != (height, width):
        raise RelightError(f"{path}: payload {payload.name} is a {header.width}x{header.height} EXR, "
                           f"the cache layer says {width}x{height}")
    if set(header.channels) != set(payload.channels):
        extra = sorted(set(header.channels) - set(payload.channels))
        missing = sorted(set(payload.channels) - set(header.channels))
        raise RelightError(f"{path}: payload {payload.name} channels differ from the cache layer's "
                           f"(unexpected {extra}, missing {missing})")
    check_channel_types(header.channels, str(path))


def read_npy_header(path: Path) -> tuple[tuple[int, ...], np.dtype]:
    """(shape, dtype) from a .npy file's header, without reading the array.

    Raises:
        RelightError: not a .npy file, an unsupported version, a malformed header, or a header
            whose shape and dtype do not account for the file's size exactly (a header claiming a
            huge array is refused before anything is allocated or mapped).
    """
    with open(path, "rb") as handle:
        try:
            version = np.lib.format.read_magic(handle)
            if version not in ((1, 0), (2, 0)):
                raise ValueError(f"unsupported .npy version {version[0]}.{version[1]}")
            read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                           else np.lib.format.read_array_header_2_0)
            shape, _, dtype = read_header(handle)
            data_offset = handle.tell()
        except (ValueError, EOFError) as error:
            reason = str(error).splitlines()[0] if str(error) else type(error).__name__
            raise RelightError(f"{path}: not a .npy array ({reason})") from None
    shape = tuple(int(n) for n in shape)
    data_bytes = math.prod(shape) * dtype.itemsize
    size = path.stat().st_size
    if data_offset + data_bytes != size:
        raise RelightError(f"{path}: .npy header claims {dtype.name}{list(shape)} ({data_bytes} bytes of data) but "
                           f"the file holds {size - data_offset}; refused before reading")
    return shape, dtype


def check_npy_header(path: Path, payload: Payload, header: tuple[tuple[int, ...], np.dtype]) -> None:
    """Refuse a .npy payload whose shape or dtype (`header`, from `read_npy_header`) differ from the layer's."""
    shape, dtype = header
    if shape != payload.shape or dtype.name != payload.dtype:
        raise RelightError(f"{path}: payload {payload.name} is {dtype.name}{list(shape)}, the cache layer says "
                           f"{payload.dtype}{list(payload.shape)}")


def check_payload(layer_path: Path, description: CacheDescription, payload: Payload) -> Path:
    """Every check of one payload file short of decoding it; returns its path.

    A header that cannot be parsed in a file shorter than recorded is reported as truncated; a
    header that parses but differs from the layer's record is reported as such, whatever the size.

    Raises:
        RelightError: one line naming the file and what is wrong with it.
    """
    path = payload_file(layer_path, payload)
    try:
        header = read_exr_header(path) if payload.format == "exr" else read_npy_header(path)
    except RelightError:
        if path.stat().st_size < payload.num_bytes:
            check_payload_bytes(path, payload)
        raise
    if payload.format == "exr":
        check_exr_header(path, payload, header, payload.shape or sub_sample_size(description))
    else:
        check_npy_header(path, payload, header)
    check_payload_bytes(path, payload)
    return path


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
    path = check_payload(layer_path, description, payload)
    channels, _ = read_exr(path)
    camera_position = description.world_from_camera[:3, 3]
    return gbuffer_from_channels(channels, payload.constants, camera_position, str(path))


def load_npy(layer_path: Path, description: CacheDescription, name: str) -> np.ndarray:
    """A .npy payload, memory-mapped, its header checked against the layer before mapping."""
    payload = description.payload(name)
    path = check_payload(layer_path, description, payload)
    return np.load(path, mmap_mode="r", allow_pickle=False)
