"""Loading a cache safely: everything is checked before anything big is allocated.

Order: the layer parses and names a supported version; every payload file exists with the size
and sha256 the layer records (streamed, so a corrupt or truncated file is refused without being
loaded); headers (EXR data window and channels, .npy shape and dtype) match the layer; then the
inputs the bake read are re-hashed, so a cache whose shot changed is reported stale, naming the
file. No pickle anywhere: .npy files are read with allow_pickle=False.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import OpenEXR

from relight_torch.cache.gbuffer_exr import gbuffer_from_channels
from relight_torch.cache.layer import CacheDescription, Payload, file_sha256
from relight_torch.errors import RelightError
from relight_torch.gbuffer import GBuffer
from relight_torch.io.exr import read_exr


def payload_path(layer_path: Path, payload: Payload) -> Path:
    """The payload's file, verified against the size and sha256 the layer records."""
    path = (layer_path.parent / payload.file).resolve()
    if not path.is_file():
        raise RelightError(f"{layer_path}: payload {payload.name} file {path} is missing")
    size = path.stat().st_size
    if size != payload.num_bytes:
        raise RelightError(f"{path}: payload {payload.name} is {size} bytes, the cache layer says "
                           f"{payload.num_bytes} (truncated or replaced)")
    if file_sha256(path) != payload.sha256:
        raise RelightError(f"{path}: payload {payload.name} does not match its sha256 (corrupt or edited)")
    return path


def check_inputs(layer_path: Path, description: CacheDescription) -> None:
    """Refuse a stale cache: an input the bake read is missing or changed since."""
    for file, digest in description.inputs.items():
        if not os.path.isfile(file):
            raise RelightError(f"{layer_path}: stale cache: input {file} is missing")
        if file_sha256(file) != digest:
            raise RelightError(f"{layer_path}: stale cache: input {file} changed since the bake; re-bake it")


def load_gbuffer(layer_path: Path, description: CacheDescription) -> GBuffer:
    """The deep framebuffer payload as a CPU GBuffer."""
    payload = description.payload("deepFramebuffer")
    path = payload_path(layer_path, payload)
    width, height = description.resolution
    s = description.supersampling
    with OpenEXR.File(str(path), header_only=True) as exr:
        (x0, y0), (x1, y1) = exr.header()["dataWindow"]  # the header is cleared on close
    found = (int(y1 - y0 + 1), int(x1 - x0 + 1))
    if found != (height * s, width * s):
        raise RelightError(f"{path}: deep framebuffer is {found[1]}x{found[0]}, the cache layer says "
                           f"{width * s}x{height * s}")
    channels, _ = read_exr(path)
    if set(channels) != set(payload.channels):
        raise RelightError(f"{path}: channels {sorted(channels)} differ from the cache layer's {sorted(payload.channels)}")
    camera_position = description.world_from_camera[:3, 3]
    return gbuffer_from_channels(channels, payload.constants, camera_position, str(path))


def load_npy(layer_path: Path, description: CacheDescription, name: str) -> np.ndarray:
    """A .npy payload, memory-mapped, its header checked against the layer before mapping."""
    payload = description.payload(name)
    path = payload_path(layer_path, payload)
    with open(path, "rb") as handle:
        try:
            version = np.lib.format.read_magic(handle)
            read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                           else np.lib.format.read_array_header_2_0)
            shape, _, dtype = read_header(handle)
        except ValueError as error:
            raise RelightError(f"{path}: not a .npy array ({error})") from None
    if tuple(shape) != payload.shape or dtype.name != payload.dtype:
        raise RelightError(f"{path}: array is {dtype.name}{list(shape)}, the cache layer says "
                           f"{payload.dtype}{list(payload.shape)}")
    return np.load(path, mmap_mode="r", allow_pickle=False)
