"""Caching cameras as `Camera`s and as rows of the cache's camera table."""

from __future__ import annotations

import numpy as np

from pipeline.scene.types import Camera
from relight_torch.multiview.views import CAMERA_COLUMNS, world_from_camera

FOCAL_LENGTH = 10.0
"""Focal length of every caching camera (tenths of a scene unit); only aperture / focal matters."""
CUBE_FORWARD = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)
"""The six view directions of an omni-directional (cube map) camera: +x, -x, +y, -y, +z, -z."""


def look_camera(
    path: str,
    position: np.ndarray,
    forward: np.ndarray,
    up: np.ndarray,
    fov_degrees: float,
    resolution: int,
    near: float,
    far: float,
) -> Camera:
    """A square pinhole camera at `position` looking along `forward` with full field of view `fov_degrees`.

    `up` need only not be parallel to `forward`; the camera's +Y is its part orthogonal to it.
    """
    forward = np.asarray(forward, np.float64) / np.linalg.norm(forward)
    up = np.asarray(up, np.float64)
    if abs(np.dot(up, forward)) > 0.999 * np.linalg.norm(up):
        up = np.roll(up, 1)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    matrix = np.eye(4)
    matrix[:3, 0], matrix[:3, 1], matrix[:3, 2], matrix[:3, 3] = right, true_up, -forward, position
    aperture = 2.0 * FOCAL_LENGTH * np.tan(np.radians(fov_degrees) / 2.0)
    return Camera(
        path=path,
        world_from_camera=matrix,
        focal_length=FOCAL_LENGTH,
        horizontal_aperture=aperture,
        vertical_aperture=aperture,
        horizontal_aperture_offset=0.0,
        vertical_aperture_offset=0.0,
        clipping_range=(float(near), float(far)),
        width=int(resolution),
        height=int(resolution),
    )


def camera_row(camera: Camera, kind: int, group: int) -> np.ndarray:
    """(C,) float64 row of the camera table (`relight_torch.multiview.views.CAMERA_COLUMNS`)."""
    return np.concatenate(
        [
            np.asarray(camera.world_from_camera, np.float64).reshape(-1),
            [
                camera.focal_length,
                camera.horizontal_aperture,
                camera.vertical_aperture,
                camera.horizontal_aperture_offset,
                camera.vertical_aperture_offset,
                *camera.clipping_range,
                camera.width,
                camera.height,
                kind,
                group,
            ],
        ]
    )


def camera_from_row(row: np.ndarray, path: str) -> Camera:
    """The `Camera` of one camera-table row."""
    values = dict(zip(CAMERA_COLUMNS, row.tolist(), strict=True))
    return Camera(
        path=path,
        world_from_camera=world_from_camera(row[None])[0],
        focal_length=values["focalLength"],
        horizontal_aperture=values["horizontalAperture"],
        vertical_aperture=values["verticalAperture"],
        horizontal_aperture_offset=values["horizontalApertureOffset"],
        vertical_aperture_offset=values["verticalApertureOffset"],
        clipping_range=(values["near"], values["far"]),
        width=int(values["width"]),
        height=int(values["height"]),
    )


def resolution_from_coverage(covered_share: float, min_resolution: int, max_resolution: int) -> int:
    """Square image size for a camera covering `covered_share` of the samples' importance.

    The paper picks one of 256, 512, 1024, 2048 by the number of covered samples; here the power
    of two nearest above max_resolution x sqrt(share), clamped to [min_resolution, max_resolution],
    so that a camera's pixels per unit of covered importance stay about constant.
    """
    wanted = max_resolution * np.sqrt(max(covered_share, 0.0))
    size = 2 ** int(np.ceil(np.log2(max(wanted, 1.0))))
    return int(np.clip(size, min_resolution, max_resolution))
