"""Placing a light by where it should land: a pixel of the frame -> the surface point it sees -> a
light transform aimed at that point, or set along its normal (as DCC tools' "place by target").

The surface point comes from the cache's deep framebuffer (`relight_torch.gbuffer.GBuffer`): the
covered sub-sample nearest the pixel's centre, its world position and geometric normal (turned
towards the camera). Transforms are (4, 4) float64 column-vector `world_from_light`; a light shines
along its local -Z axis (UsdLux), and placement keeps the light's own axis scales.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from relight_torch.gbuffer import GBuffer
from relight_torch.lights.light import Light, LightKind

# Intensity of a new light with `normalize` on, over its distance squared, for an irradiance of
# about 1 where it faces (disk and rect: E = I / d^2; sphere: I / 4 d^2; cylinder: I / pi d^2);
# distant: E = I; dome (not normalised): radiance I.
_NEW_LIGHT_INTENSITY = {
    LightKind.SPHERE: 4.0,
    LightKind.DISK: 1.0,
    LightKind.RECT: 1.0,
    LightKind.CYLINDER: math.pi,
    LightKind.DISTANT: 1.0,
    LightKind.DOME: 0.3,
}
_NEW_LIGHT_SIZE = 0.1
"""A new area light's radius (or half-width) as a fraction of its distance to what it lights."""


@dataclass(frozen=True)
class SurfacePoint:
    """What a pixel sees: world `position` (3,) and unit `normal` (3,) on the camera's side."""

    position: np.ndarray
    normal: np.ndarray


class SurfaceLookup:
    """Pixel -> `SurfacePoint` of one deep framebuffer.

    Args:
        gbuffer: the cache's deep framebuffer, sub-sample image (H * s, W * s).
        supersampling: s, sub-samples per pixel side.
    """

    def __init__(self, gbuffer: GBuffer, supersampling: int):
        height, width = gbuffer.image_size
        self.supersampling = supersampling
        self.size = (width // supersampling, height // supersampling)
        # (H * s * W * s,) sample index of each sub-sample, -1 where uncovered.
        self._sample_at = np.full(height * width, -1, np.int64)
        self._sample_at[gbuffer.pixel_index.cpu().numpy()] = np.arange(gbuffer.num_samples)
        # Kept as the G-buffer holds them (float32); the one sample looked up is widened.
        self._position = gbuffer.position.cpu().numpy()
        self._normal = gbuffer.geometric_normal.cpu().numpy()
        s = supersampling
        offsets = np.stack(np.meshgrid(np.arange(s), np.arange(s), indexing="ij"), -1).reshape(-1, 2)
        # Sub-samples of a pixel, nearest its centre first.
        self._offsets = offsets[np.argsort(np.abs(offsets - (s - 1) / 2).sum(-1), kind="stable")]

    def at(self, x: int, y: int) -> SurfacePoint | None:
        """The surface seen at pixel column `x`, row `y` (row 0 at the top); None for sky.

        Raises:
            ValueError: the pixel is outside the image.
        """
        width, height = self.size
        if not (0 <= x < width and 0 <= y < height):
            raise ValueError(f"pixel ({x}, {y}) is outside the {width}x{height} image")
        s = self.supersampling
        rows, cols = y * s + self._offsets[:, 0], x * s + self._offsets[:, 1]
        samples = self._sample_at[rows * width * s + cols]
        covered = samples[samples >= 0]
        if covered.size == 0:
            return None
        sample = covered[0]
        normal = self._normal[sample].astype(np.float64)
        # Renormalised: the cache may store normals in half precision.
        return SurfacePoint(self._position[sample].astype(np.float64), normal / np.linalg.norm(normal))


def aimed_at(world_from_light: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """The light turned in place so that its -Z axis points at world point `target` (3,).

    Args:
        up: (3,) world direction the light's +Y should lean towards (the camera's up).

    Raises:
        ValueError: the target is the light's own position.
    """
    position = world_from_light[:3, 3]
    forward = target - position
    if not np.linalg.norm(forward) > 0.0:
        raise ValueError("the target point is the light's own position")
    return oriented(position, forward, _axis_scales(world_from_light), up)


def along_normal(world_from_light: np.ndarray, point: SurfacePoint, distance: float, up: np.ndarray) -> np.ndarray:
    """The light moved to `distance` (world units) from the surface point along its normal, facing it."""
    position = point.position + distance * point.normal
    return oriented(position, -point.normal, _axis_scales(world_from_light), up)


def facing(world_from_light: np.ndarray, direction: np.ndarray, up: np.ndarray) -> np.ndarray:
    """The light turned in place so that its -Z axis is `direction` (3,) (a distant light's travel)."""
    return oriented(world_from_light[:3, 3], direction, _axis_scales(world_from_light), up)


def oriented(position: np.ndarray, forward: np.ndarray, scales: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(4, 4) world_from_light at `position` whose -Z is `forward`, axes scaled by `scales` (3,)."""
    z_axis = -forward / np.linalg.norm(forward)
    for lean in (up, np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0])):
        x_axis = np.cross(lean, z_axis)
        if np.linalg.norm(x_axis) > 1e-6:  # `lean` not parallel to the light's axis
            break
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(z_axis, x_axis)
    world_from_light = np.eye(4)
    world_from_light[:3, :3] = np.stack([x_axis, y_axis, z_axis], axis=1) * scales
    world_from_light[:3, 3] = position
    return world_from_light


def _axis_scales(world_from_light: np.ndarray) -> np.ndarray:
    scales: np.ndarray = np.linalg.norm(world_from_light[:3, :3], axis=0)
    return scales


def new_light(kind: LightKind, path: str, lookup: SurfaceLookup, world_from_camera: np.ndarray) -> Light:
    """A light of `kind` at prim `path` facing the surface seen at the image centre from half the
    camera's distance along its normal, sized and bright enough to be seen (`_NEW_LIGHT_INTENSITY`).

    Args:
        world_from_camera: (4, 4) column-vector camera transform (the camera looks along -Z).
    """
    up, camera = world_from_camera[:3, 1], world_from_camera[:3, 3]
    width, height = lookup.size
    point = lookup.at(width // 2, height // 2)
    if point is None:  # sky at the centre: one unit in front of the camera, facing along its view
        forward = -world_from_camera[:3, 2] / np.linalg.norm(world_from_camera[:3, 2])
        distance, position, normal = 1.0, camera + forward, -forward
    else:
        distance = 0.5 * float(np.linalg.norm(point.position - camera)) or 1.0
        position, normal = point.position + distance * point.normal, point.normal
    size = _NEW_LIGHT_SIZE * distance
    area = kind not in (LightKind.DISTANT, LightKind.DOME)
    return Light(
        path=path,
        kind=kind,
        world_from_light=oriented(position, -normal, np.ones(3), up),
        intensity=_NEW_LIGHT_INTENSITY[kind] * (distance**2 if area else 1.0),
        normalize=kind is not LightKind.DOME,
        radius=size if kind is not LightKind.CYLINDER else size / 2,
        width=2 * size,
        height=2 * size,
        length=2 * size,
        light_group=path.rsplit("/", 1)[-1],
    )
