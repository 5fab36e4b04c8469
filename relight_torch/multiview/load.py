"""Reading a 'multiview' cache: the camera table and one deep framebuffer per caching camera.

Payloads (written by `pipeline.bake.multiview.bake`): `cameras` (.npy, (K, C) float64, columns
`views.CAMERA_COLUMNS`), `view000` ... (EXR deep framebuffers, each at its own camera's
resolution, so each header is checked against its row of the table rather than the layer's
resolution), and the direct cache's `occluders`, `occluderObjects`, `objectPaths`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from relight_torch.cache.gbuffer_exr import gbuffer_from_channels
from relight_torch.cache.layer import CacheDescription
from relight_torch.cache.load import load_npy, read_payload_exr
from relight_torch.errors import RelightError
from relight_torch.gbuffer import GBuffer
from relight_torch.multiview.views import camera_column, check_camera_table, world_from_camera


def view_payload_name(k: int) -> str:
    """Payload name of caching camera k's deep framebuffer."""
    return f"view{k:03d}"


def load_camera_table(layer_path: Path, description: CacheDescription) -> np.ndarray:
    """The (K, C) float64 camera table, checked.

    Raises:
        RelightError: the payload is missing, corrupt or malformed.
    """
    table = np.array(load_npy(layer_path, description, "cameras"), dtype=np.float64)
    try:
        check_camera_table(table, f"{layer_path}: payload cameras")
    except ValueError as error:
        raise RelightError(str(error)) from None
    return table


def _image_size(table: np.ndarray, k: int, layer_path: Path) -> tuple[int, int]:
    if not 0 <= k < table.shape[0]:
        raise RelightError(f"{layer_path}: payload {view_payload_name(k)} has no row in the camera table")
    return int(camera_column(table, "height")[k]), int(camera_column(table, "width")[k])


def load_view_gbuffers(layer_path: Path, description: CacheDescription, table: np.ndarray) -> list[GBuffer]:
    """Every caching camera's deep framebuffer as a CPU GBuffer, headers checked against the table."""
    gbuffers = []
    positions = world_from_camera(table)[:, :3, 3]
    for k in range(table.shape[0]):
        payload = description.payload(view_payload_name(k))
        path, channels = read_payload_exr(layer_path, description, payload, _image_size(table, k, layer_path))
        gbuffers.append(gbuffer_from_channels(channels, payload.constants, positions[k], str(path)))
    return gbuffers
