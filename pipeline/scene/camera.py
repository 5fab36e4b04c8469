"""Pinhole cameras from UsdGeom.Camera: reading, primary rays and projection.

Film conventions: the camera looks down its local -Z with +Y up. A point of the film (aperture)
plane at x_film, y_film (tenths of a scene unit, like the apertures) sees the direction
(x_film, y_film, -focal_length). Pixel (row 0, col 0) is the top-left of the image; pixel
coordinates (x = column, y = row, continuous) put the centre of pixel (r, c) at (c + 0.5, r + 0.5):

    x_film = (x / width - 0.5) * horizontal_aperture + horizontal_aperture_offset
    y_film = (0.5 - y / height) * vertical_aperture + vertical_aperture_offset

Aspect ratio: when width / height differs from the authored aperture aspect, the HORIZONTAL
aperture is kept and the vertical one becomes horizontal_aperture * height / width ("horizontal
fit", as a film back gate would be masked). Hydra's default policy (expandAperture) grows
whichever aperture is too small instead; the two agree whenever the aspects match.

Resolution: the stage's UsdRender.Settings (the one named by the stage's renderSettingsPrimPath
metadata, else the first found) gives width and height; else 640 x 480. Explicit width/height
override either.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from pxr import Usd, UsdGeom, UsdRender

from pipeline.errors import RelightError, warn
from pipeline.scene.types import Camera
from relight_torch import xform

DEFAULT_RESOLUTION = (640, 480)


def _render_settings(stage: Usd.Stage) -> UsdRender.Settings | None:
    """The stage's designated render settings, else the first UsdRender.Settings prim."""
    settings = UsdRender.Settings.GetStageRenderSettings(stage)
    if settings:
        return settings
    for prim in stage.Traverse():
        if prim.IsA(UsdRender.Settings):
            return UsdRender.Settings(prim)
    return None


def image_resolution(stage: Usd.Stage, width: int | None = None, height: int | None = None) -> tuple[int, int]:
    """(width, height) in pixels: explicit values, else the render settings, else 640 x 480.

    Raises:
        RelightError: an explicit or authored size is not a positive integer.
    """
    default_width, default_height = DEFAULT_RESOLUTION
    settings = _render_settings(stage)
    if settings is not None:
        default_width, default_height = settings.GetResolutionAttr().Get()
    size = (default_width if width is None else width, default_height if height is None else height)
    for name, value in zip(("width", "height"), size, strict=True):
        if int(value) != value or value <= 0:
            raise RelightError(f"image {name} must be a positive integer, got {value}")
    return int(size[0]), int(size[1])


def read_camera(camera: UsdGeom.Camera, time: Usd.TimeCode, width: int, height: int) -> Camera:
    """One perspective UsdGeom.Camera at `time`, conformed to a width x height image."""
    try:
        gf_camera = camera.GetCamera(time)
    except Exception:  # pxr's Tf.ErrorException: an xformOp authored with a value of another type
        raise RelightError(f"camera {camera.GetPath()}: {xform.unreadable_op(camera.GetPrim(), time)}") from None
    clipping = gf_camera.clippingRange
    horizontal_aperture = float(gf_camera.horizontalAperture)
    return Camera(
        path=str(camera.GetPath()),
        world_from_camera=np.array(gf_camera.transform, np.float64).T,
        focal_length=float(gf_camera.focalLength),
        horizontal_aperture=horizontal_aperture,
        vertical_aperture=horizontal_aperture * height / width,
        horizontal_aperture_offset=float(gf_camera.horizontalApertureOffset),
        vertical_aperture_offset=float(gf_camera.verticalApertureOffset),
        clipping_range=(float(clipping.min), float(clipping.max)),
        width=width,
        height=height,
        exposure_scale=float(camera.ComputeLinearExposureScale(time)),
    )


def read_cameras(
    stage: Usd.Stage,
    time: Usd.TimeCode,
    width: int | None = None,
    height: int | None = None,
    warnings: list[str] | None = None,
) -> dict[str, Camera]:
    """Every perspective camera of the stage, keyed by prim path.

    Orthographic cameras are skipped with a warning (the renderers are pinhole only).

    Args:
        stage: the composed stage. time: time code to read.
        width, height: image size overrides in pixels (see `image_resolution`).
        warnings: sink for one-line warnings.
    """
    width, height = image_resolution(stage, width, height)
    cameras = {}
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.Camera):
            continue
        camera = UsdGeom.Camera(prim)
        if camera.GetProjectionAttr().Get(time) == UsdGeom.Tokens.orthographic:
            warn(f"camera {prim.GetPath()} is orthographic, which is not supported; skipped", warnings)
            continue
        cameras[str(prim.GetPath())] = read_camera(camera, time, width, height)
    return cameras


def _film_from_pixel(camera: Camera, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Film-plane coordinates of continuous pixel coordinates (module docstring)."""
    x_film = (x / camera.width - 0.5) * camera.horizontal_aperture + camera.horizontal_aperture_offset
    y_film = (0.5 - y / camera.height) * camera.vertical_aperture + camera.vertical_aperture_offset
    return x_film, y_film


def camera_rays(
    camera: Camera, pixel_offsets: np.ndarray | None = None, rows: tuple[int, int] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """One primary ray per pixel.

    Args:
        camera: the camera and its image size H x W.
        pixel_offsets: (H, W, 2) sample position within each pixel in [0, 1): [..., 0] along
            the row (rightwards), [..., 1] down the column; None means the centre (0.5, 0.5).
        rows: only the pixel rows [first, last) (H = last - first above); None: all rows.

    Returns:
        origins (H, W, 3) float32 world-space camera position,
        directions (H, W, 3) float32 unit world-space directions.
    """
    first, last = rows or (0, camera.height)
    shape = (last - first, camera.width)
    if pixel_offsets is None:
        pixel_offsets = np.full(shape + (2,), 0.5)
    elif pixel_offsets.shape != shape + (2,):
        raise ValueError(f"pixel_offsets must have shape {shape + (2,)}, got {pixel_offsets.shape}")
    x = np.arange(camera.width)[None, :] + pixel_offsets[..., 0]
    y = np.arange(first, last)[:, None] + pixel_offsets[..., 1]
    x_film, y_film = _film_from_pixel(camera, x, y)
    directions_camera = np.stack(np.broadcast_arrays(x_film, y_film, -camera.focal_length), axis=-1)
    directions = directions_camera @ camera.world_from_camera[:3, :3].T
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    origins = np.broadcast_to(camera.world_from_camera[:3, 3], directions.shape)
    return origins.astype(np.float32), directions.astype(np.float32)


def crop(camera: Camera, left: int, top: int, width: int, height: int) -> Camera:
    """The window of `camera`'s image of `width` x `height` pixels from pixel (row `top`, column
    `left`), as a camera of its own: its pixels see exactly what those pixels see (the film
    window's apertures and offsets, the same pinhole and transform).

    Raises:
        ValueError: the window is empty or leaves the image.
    """
    if not (0 <= left < left + width <= camera.width and 0 <= top < top + height <= camera.height):
        raise ValueError(
            f"crop {width}x{height} at ({left}, {top}) leaves the {camera.width}x{camera.height} image of {camera.path}"
        )
    return dataclasses.replace(
        camera,
        horizontal_aperture=camera.horizontal_aperture * width / camera.width,
        vertical_aperture=camera.vertical_aperture * height / camera.height,
        horizontal_aperture_offset=camera.horizontal_aperture_offset
        + camera.horizontal_aperture * ((left + width / 2) / camera.width - 0.5),
        vertical_aperture_offset=camera.vertical_aperture_offset
        + camera.vertical_aperture * (0.5 - (top + height / 2) / camera.height),
        width=width,
        height=height,
    )


def camera_from_world(camera: Camera) -> np.ndarray:
    """(4, 4) float64 column-vector transform from world space to the camera's space."""
    return np.linalg.inv(camera.world_from_camera)


def project(camera: Camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project world points into the image (the inverse of `camera_rays`).

    Args:
        camera: the camera.
        points: (N, 3) world-space points.

    Returns:
        pixels (N, 2) float64 continuous (x = column, y = row) coordinates, the centre of pixel
        (r, c) being (c + 0.5, r + 0.5); NaN for points not in front of the camera.
        depth (N,) float64 distance in front of the camera along its view axis (-Z of camera
        space), in camera-space units; <= 0 behind the camera.
    """
    matrix = camera_from_world(camera)
    points_camera = np.asarray(points, np.float64) @ matrix[:3, :3].T + matrix[:3, 3]
    depth = -points_camera[:, 2]
    in_front = depth > 0
    safe_depth = np.where(in_front, depth, 1.0)
    x_film = camera.focal_length * points_camera[:, 0] / safe_depth
    y_film = camera.focal_length * points_camera[:, 1] / safe_depth
    x = ((x_film - camera.horizontal_aperture_offset) / camera.horizontal_aperture + 0.5) * camera.width
    y = (0.5 - (y_film - camera.vertical_aperture_offset) / camera.vertical_aperture) * camera.height
    pixels = np.where(in_front[:, None], np.stack((x, y), axis=-1), np.nan)
    return pixels, depth
