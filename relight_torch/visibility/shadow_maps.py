"""Shadows from depth maps rendered in torch: the `Visibility` of devices without Embree.

One map per light, placed at the light's centre and rebuilt only when the light's geometry
changes (`depth_maps`, rasterised exactly by `raster`):

    sphere, disk, rect, cylinder   a cube map (6 faces) at the light's origin;
    the same with ShapingAPI       one perspective map along the light's -Z axis when the cone's
                                   half-angle (+ `SPOT_MARGIN_DEGREES`) is at most
                                   `max_spot_half_angle` (60 by default: beyond it a perspective
                                   texel at the axis is more than 1.7x a cube face's, and near 90
                                   degrees the projection degenerates), else the cube map;
    distant                        an orthographic map along the light's direction whose window
                                   covers the receivers (grown, and the map rebuilt, when a query
                                   falls outside it), clipped to the occluders' footprint;
    dome                           not supported: raises; use Embree shadows.

Two lookups answer a light sample (point p, direction d, distance L to the sample):

    'pcss' (default)  one PCF tap per sample, placed where the sample's segment reaches the
                      blockers' depth (percentage-closer soft shadows with the light's own
                      samples as the filter, `_percentage_closer`): at most three map reads
                      per sample, about 12x cheaper than the march. Less exact where blockers lie
                      at several depths (at the foot of a box): relit Cornell box images are
                      44.3-48.0 dB from Embree-shadowed ones where the march's are 50.3-54.5
                      (docs/GATHER.md).
    'march'           the segment tested at `march_steps` + 1 points, below.

The march tests the segment p -> p + L d at `march_steps` + 1 points (for distant lights up to
the map's top plane) and looks each point x up in the map from the light's centre. x is *behind* the stored surface
when its depth exceeds the stored depth by a slope-scaled bias: one texel footprint at that
depth plus the texel's depth slope (`MapLookup.slope`), both from the map's texel size, never a
world epsilon. The segment is blocked where consecutive points change side (in front <-> behind)
while the stored depth stays continuous (it changes by no more than twice the step plus the
bias): a real surface was crossed. A change of side across a depth discontinuity is the
segment passing a silhouette's shadow-volume wall, not an occluder, and does not count. For a
point light every march point falls in the texel of p, and the test is the classic shadow map
comparison.

Both lookups take the receiver's own surface out first: a stored depth equal (within one footprint times
1 + tan of the incidence) to the depth of the receiver's tangent plane along that texel's ray is
the receiver itself, and a segment leaving a surface towards its front side can never cross that
plane. This is what removes acne on lit surfaces, and what keeps an area light whose centre lies
below a receiver's horizon from shadowing the receiver by its own plane.

Percentage-closer filtering of the march, per sample: every light sample is one PCF tap. Its
lookups fall where its own ray towards its point of the light projects into the map, so the taps of a point
spread over the light's projection at the occluder's depth (the kernel width follows the light's
size and the blocker-receiver distance, as in PCSS, without a blocker search); each sample's
lookups are further offset by a sub-texel jitter (a 2-D R2 sequence over the S samples), a
one-texel box filter that smooths texel staircases. The relighter averages the S binary results:
the fraction of unblocked taps. A delta light has one sample and a hard, texel-exact shadow.

Known limits: occluders thinner than the march step's projection at their depth may be stepped
over (raise `march_steps`); parts of a spot map's surroundings outside its field of view cast
no shadow; curved receivers near the terminator of an area light may show slight acne (the
tangent-plane test is exact for planes only).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from relight_torch.errors import RelightError
from relight_torch.lights.geometry import LightFrame, transform_rows
from relight_torch.lights.light import Light, LightKind
from relight_torch.math.frame import orthonormal_basis
from relight_torch.visibility.depth_maps import CubeMap, DepthMap, MapSample, OrthoMap, PinholeMaps
from relight_torch.visibility.opacity import OpacityTable

# Bias floor for "behind the stored surface", in texel footprints at the stored depth.
BEHIND_TEXELS = 1.0
# Tolerance of the receiver-plane test, in texel footprints times (1 + tan incidence).
RECEIVER_PLANE_TEXELS = 1.0
# Largest tan(incidence) the receiver-plane tolerance grows to.
MAX_RECEIVER_SLOPE = 16.0
# Field of view added around a spot light's cone (its softness lies inside the cone).
SPOT_MARGIN_DEGREES = 5.0
# Height of a distant map's plane above the highest occluder, relative to the occluders' extent.
TOP_MARGIN_FRACTION = 1e-3
# Largest half-angle of a distant light's cone used to widen its window (tan grows without bound).
MAX_DISTANT_WINDOW_ANGLE = math.radians(80.0)
# Low-discrepancy R2 sequence (Roberts 2018): generalised golden ratio steps per axis.
_R2_STEPS = (0.7548776662466927, 0.5698402909980532)
# Depth of the blocker search's taps, as a fraction of the receiver's depth (see `_percentage_closer`;
# 0.125 / 0.25 / 0.5: 41.8 / 42.5 / 42.9 dB against Embree on the Cornell box's focus edit).
SEARCH_DEPTH_FRACTION = 0.5
# How far behind a tap its texel's surface may lie and still block, as a fraction of the tap's
# distance in depth to the receiver (0.25 / 0.5 / 1.0: 46.7 / 47.1 / 42.1 dB against Embree on the
# Cornell box after a move; see docs/GATHER.md).
TAP_TOLERANCE_FRACTION = 0.5
# Lookup schemes of `ShadowMapVisibility`.
LOOKUPS = ("pcss", "march")
# Light fields a map depends on.
_MAP_FIELDS = ("kind", "radius", "width", "height", "length", "angle")


class ShadowMapVisibility:
    """Shadow-map visibility of a cache's occluder triangles, on their device.

    Args:
        occluders: (T, 3, 3) world triangle corners (float tensor; the maps' device and dtype).
        resolution: texels per side of every map face.
        march_steps: segment steps per light sample of the 'march' lookup (area and distant
            lights with an angle).
        receivers: (M, 3) world points the relighter will query (e.g. the deep framebuffer's
            positions), or None; distant maps cover their bounds from the start, so that no
            later query grows the window.
        max_spot_half_angle: largest cone half-angle (degrees) given a perspective map.
        lookup: 'pcss' (one PCF tap per sample, the default) or 'march' (see the module doc).
        opacity: the occluders' non-opaque triangles (holes rasterised as no depth), or None.

    Attributes:
        num_builds: maps built so far (tests check that a light is mapped once).
        seconds: this process's CPU seconds spent so far in 'build' (maps) and 'lookup' (the
            queries less their builds), for benchmarks.
    """

    def __init__(
        self,
        occluders: torch.Tensor,
        resolution: int = 1024,
        march_steps: int = 16,
        receivers: torch.Tensor | None = None,
        max_spot_half_angle: float = 60.0,
        lookup: str = "pcss",
        opacity: OpacityTable | None = None,
    ):
        if not isinstance(occluders, torch.Tensor) or occluders.dim() != 3 or occluders.shape[1:] != (3, 3):
            raise ValueError(
                f"occluders must be a (T, 3, 3) tensor of triangle corners, got "
                f"{getattr(occluders, 'shape', type(occluders).__name__)}"
            )
        if not occluders.is_floating_point():
            raise ValueError(f"occluders must be a floating-point tensor, got {occluders.dtype}")
        if lookup not in LOOKUPS:
            raise ValueError(f"lookup must be one of {LOOKUPS}, got {lookup!r}")
        if resolution < 2 or march_steps < 1:
            raise ValueError(f"resolution must be >= 2 and march_steps >= 1, got {resolution} and {march_steps}")
        self.occluders = occluders
        self.opacity = opacity
        self.resolution = resolution
        self.march_steps = march_steps
        self.lookup = lookup
        self.receivers = None if receivers is None else receivers.to(occluders.device, occluders.dtype).reshape(-1, 3)
        self.max_spot_half_angle = max_spot_half_angle
        self.thread_safe = False  # maps are built and cached on first use
        self.num_builds = 0
        self.seconds: dict[str, float] = {"build": 0.0, "lookup": 0.0}  # process time spent
        self._maps: dict[str, tuple[tuple, DepthMap]] = {}
        # Texel directions shared by every cube map (they do not depend on the light's position).
        self._cube_directions: torch.Tensor | None = None

    def occluder_distance(
        self,
        light: Light,
        points: torch.Tensor,
        normals: torch.Tensor,
        directions: torch.Tensor,
        distances: torch.Tensor,
    ) -> torch.Tensor:
        """(N, S) distance to the first occluder (inf where visible); see `Visibility`.

        The distance is where the march found the crossing (mid-step) or where the PCF tap was
        taken, for ShadowAPI distances.

        Raises:
            RelightError: for a dome light (shadow maps cannot represent it).
        """
        start, built = time.process_time(), self.seconds["build"]
        dtype = self.occluders.dtype
        result_dtype = distances.dtype
        points, normals = points.to(dtype), normals.to(dtype)
        directions, distances = directions.to(dtype), distances.to(dtype)
        depth_map = self.depth_map(light, points)
        if light.kind is LightKind.DISTANT:
            height = depth_map.project(points)[2].unsqueeze(-1)
            rising = -(directions * depth_map.face_from_world[0, 2]).sum(-1)
            reach = torch.where(rising > 0, height / rising.clamp_min(torch.finfo(dtype).tiny), 0.0).clamp_min(0.0)
        else:
            reach = torch.where(torch.isfinite(distances), distances, torch.zeros_like(distances))
        if self.lookup == "march":
            found = _march(depth_map, points, normals, directions, reach, self.march_steps)
        else:
            found = _percentage_closer(depth_map, points, normals, directions, reach)
        self.seconds["lookup"] += time.process_time() - start - (self.seconds["build"] - built)
        return found.to(result_dtype)

    def depth_map(self, light: Light, points: torch.Tensor | None = None) -> DepthMap:
        """The light's map, built on first use and whenever its geometry (or a distant window) changes.

        Args:
            light: the light.
            points: (N, 3) receivers about to be queried (distant lights: the window covers them).
        """
        if light.kind is LightKind.DOME:
            raise RelightError(
                f"{light.path}: DomeLight shadows need Embree: shadow maps cannot represent a dome; "
                f"use shadows='embree'"
            )
        key = _map_key(light)
        cached = self._maps.get(light.path)
        depth_map: DepthMap
        if light.kind is LightKind.DISTANT:
            window = self._distant_window(light, points)
            if cached is not None and cached[0][:-1] == key and _contains(cached[0][-1], window):
                return cached[1]
            if cached is not None and cached[0][:-1] == key:
                window = _union(cached[0][-1], window)
            depth_map = self._distant_map(light, window)
            key = key + (window,)
        elif cached is not None and cached[0] == key:
            return cached[1]
        else:
            depth_map = self._pinhole_map(light)
        start = time.process_time()
        depth_map.build(self.occluders, self.opacity)
        self.seconds["build"] += time.process_time() - start
        self.num_builds += 1
        self._maps[light.path] = (key, depth_map)
        return depth_map

    def _pinhole_map(self, light: Light) -> PinholeMaps:
        like = self.occluders
        centre = torch.as_tensor(light.world_from_light[:3, 3], device=like.device, dtype=like.dtype)
        shaping = light.shaping
        if shaping is not None and shaping.cone_angle + SPOT_MARGIN_DEGREES <= self.max_spot_half_angle:
            axis = -np.asarray(light.world_from_light[:3, 2], np.float64)
            forward = torch.as_tensor(axis / np.linalg.norm(axis), device=like.device, dtype=like.dtype)
            right, up = orthonormal_basis(forward)
            tan_half_fov = math.tan(math.radians(shaping.cone_angle + SPOT_MARGIN_DEGREES))
            return PinholeMaps(centre, torch.stack((right, up, forward)).unsqueeze(0), tan_half_fov, self.resolution)
        front = None
        if light.kind in (LightKind.RECT, LightKind.DISK):  # one-sided: emits towards local -Z
            front = LightFrame.of(light, like).normal_to_world_unit(like.new_tensor([0.0, 0.0, -1.0]))
        cube = CubeMap(centre, self.resolution, self._cube_directions, front)
        self._cube_directions = cube.directions
        return cube

    def _distant_frame(self, light: Light) -> torch.Tensor:
        """(3, 3) rows right, up, forward (= the light's -direction) of a distant light's map."""
        to_light = np.asarray(light.world_from_light[:3, 2], np.float64)
        forward = torch.as_tensor(
            -to_light / np.linalg.norm(to_light), device=self.occluders.device, dtype=self.occluders.dtype
        )
        return torch.stack((*orthonormal_basis(forward), forward))

    def _distant_window(self, light: Light, points: torch.Tensor | None) -> tuple[float, float, float, float]:
        """(u_low, v_low, u_high, v_high) of the receivers' window in the map's frame.

        The receivers' bounds (queries and `receivers`), widened by how far a ray of the light's
        cone travels sideways up to the top plane, intersected with the occluders' bounds (no
        shadow falls outside them); the occluders' bounds when that is empty.
        """
        frame = self._distant_frame(light)
        corners = transform_rows(self.occluders.reshape(-1, 3), frame)
        occluder_low, occluder_high = corners[:, :2].amin(0), corners[:, :2].amax(0)
        receivers = [p.reshape(-1, 3) for p in (points, self.receivers) if p is not None]
        if not receivers:
            return _as_window(occluder_low, occluder_high)
        local = transform_rows(torch.cat(receivers).to(frame.dtype), frame)
        theta = min(math.radians(light.angle) / 2.0, MAX_DISTANT_WINDOW_ANGLE)
        margin = (local[:, 2].amax() - corners[:, 2].amin()).clamp_min(0.0) * math.tan(theta)
        low = torch.maximum(local[:, :2].amin(0) - margin, occluder_low)
        high = torch.minimum(local[:, :2].amax(0) + margin, occluder_high)
        if bool((low > high).any()):
            return _as_window(occluder_low, occluder_high)
        return _as_window(low, high)

    def _distant_map(self, light: Light, window: tuple[float, float, float, float]) -> OrthoMap:
        frame = self._distant_frame(light)
        corners = transform_rows(self.occluders.reshape(-1, 3), frame)
        extent = float((corners.amax(0) - corners.amin(0)).max())
        top = float(corners[:, 2].amin()) - TOP_MARGIN_FRACTION * extent
        u_low, v_low, u_high, v_high = window
        # Half a texel of padding keeps the window's edges inside texels.
        side = max(u_high - u_low, v_high - v_low, TOP_MARGIN_FRACTION * extent)
        half_size = 0.5 * side * (1.0 + 1.0 / self.resolution)
        centre_local = torch.tensor(
            (0.5 * (u_low + u_high), 0.5 * (v_low + v_high), top), device=frame.device, dtype=frame.dtype
        )
        return OrthoMap(frame, centre_local @ frame, half_size, self.resolution)


def _map_key(light: Light) -> tuple:
    """What a light's map depends on: its transform, size and kind, and a spot's cone."""
    transform = np.ascontiguousarray(light.world_from_light, np.float64).tobytes()
    cone = None if light.shaping is None else light.shaping.cone_angle
    return (transform, cone) + tuple(getattr(light, name) for name in _MAP_FIELDS)


def _as_window(low: torch.Tensor, high: torch.Tensor) -> tuple[float, float, float, float]:
    return (float(low[0]), float(low[1]), float(high[0]), float(high[1]))


def _contains(outer: tuple, inner: tuple) -> bool:
    return outer[0] <= inner[0] and outer[1] <= inner[1] and outer[2] >= inner[2] and outer[3] >= inner[3]


def _union(first: tuple, second: tuple) -> tuple:
    return (min(first[0], second[0]), min(first[1], second[1]), max(first[2], second[2]), max(first[3], second[3]))


def _sample_jitter(num_samples: int, like: torch.Tensor) -> torch.Tensor:
    """(S, 2) sub-texel offsets in [-0.5, 0.5): the R2 sequence, sample 0 at the texel's own point."""
    index = torch.arange(num_samples, device=like.device, dtype=torch.float64).unsqueeze(-1)
    steps = torch.tensor(_R2_STEPS, device=like.device, dtype=torch.float64)
    return (torch.remainder(0.5 + index * steps, 1.0) - 0.5).to(like.dtype)


def _stored_without_receiver(
    depth_map: DepthMap,
    stored: torch.Tensor,
    ray_origin: torch.Tensor,
    ray_direction: torch.Tensor,
    points: torch.Tensor,
    normals: torch.Tensor,
) -> torch.Tensor:
    """Stored depths (N, S) with the receivers' own tangent planes replaced by inf (see the module doc)."""
    cos = (normals * ray_direction).sum(-1)
    abs_cos = cos.abs()
    tiny = torch.finfo(cos.dtype).tiny
    plane = ((points - ray_origin) * normals).sum(-1) / torch.where(abs_cos > tiny, cos, torch.ones_like(cos))
    tan = torch.sqrt((1.0 - abs_cos.square()).clamp_min(0.0)) / abs_cos.clamp_min(1.0 / MAX_RECEIVER_SLOPE)
    finite = torch.isfinite(stored)
    footprint = depth_map.footprint(torch.where(finite, stored, torch.zeros_like(stored)))
    own = finite & (abs_cos > tiny) & ((stored - plane).abs() <= RECEIVER_PLANE_TEXELS * footprint * (1.0 + tan))
    return torch.where(own, torch.full_like(stored, torch.inf), stored)


def _march(
    depth_map: DepthMap,
    points: torch.Tensor,
    normals: torch.Tensor,
    directions: torch.Tensor,
    reach: torch.Tensor,
    num_steps: int,
) -> torch.Tensor:
    """Distance (N, S) along each sample's segment to the first surface it crosses, inf if none.

    Args:
        depth_map: the light's built map.
        points: (N, 3) receivers; normals: (N, 3) their unit geometric normals.
        directions: (N, S, 3) unit directions of the segments; reach: (N, S) their lengths.
        num_steps: steps along each segment (num_steps + 1 points, from the receiver to the light
            sample: a sample sits at depth 0 (point light) or on the light's surface, in front of
            whatever surrounds the light).
    """
    num_points, num_samples = reach.shape
    jitter = _sample_jitter(num_samples, points).expand(num_points, num_samples, 2)
    p = points.unsqueeze(1)
    n = normals.unsqueeze(1)
    found = torch.full_like(reach, torch.inf)
    previous = None
    for fraction in np.linspace(0.0, 1.0, num_steps + 1):
        along = reach * float(fraction)
        look = depth_map.lookup(p + along.unsqueeze(-1) * directions, jitter)
        stored = _stored_without_receiver(depth_map, look.stored, look.ray_origin, look.ray_direction, p, n)
        finite = torch.isfinite(stored)
        bias = BEHIND_TEXELS * depth_map.footprint(torch.where(finite, stored, look.depth)) + look.slope
        behind = finite & (look.depth - stored > bias)
        if previous is not None:
            previous_along, previous_stored, previous_behind = previous
            jump = (stored - previous_stored).abs()
            continuous = finite & torch.isfinite(previous_stored) & (jump <= 2.0 * (along - previous_along) + bias)
            crossed = (behind != previous_behind) & continuous & torch.isinf(found)
            found = torch.where(crossed, 0.5 * (along + previous_along), found)
        previous = (along, stored, behind)
    return found


@dataclass(frozen=True)
class _Segments:
    """N points' S shadow segments p -> p + reach d, coordinates as separate (N, S) or (N, 1) tensors
    (see `DepthMap.project_components`).

    Attributes:
        point: (x, y, z) each (N, 1); normal: (N, 1, 3) unit normals; point_normal: (N, 1) p.n.
        direction: (x, y, z) each (N, S) unit directions.
        reach: (N, S) lengths; receiver_depth: (N, 1) the points' map depths; span: (N, S) the
            receiver's depth minus the segment end's (at least the dtype's tiny).
    """

    point: tuple[torch.Tensor, torch.Tensor, torch.Tensor]
    normal: torch.Tensor
    point_normal: torch.Tensor
    direction: tuple[torch.Tensor, torch.Tensor, torch.Tensor]
    reach: torch.Tensor
    receiver_depth: torch.Tensor
    span: torch.Tensor

    def rows(self, index: torch.Tensor) -> _Segments:
        """The segments of the points `index` (M,) long."""
        pick = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        fields: dict[str, Any] = {
            name: tuple(t[index] for t in value) if isinstance(value, tuple) else value[index]
            for name, value in pick.items()
        }
        return _Segments(**fields)


def _tap(
    depth_map: DepthMap, segments: _Segments, blocker_depth: torch.Tensor, jitter: tuple[torch.Tensor, ...]
) -> tuple[torch.Tensor, ...]:
    """One PCF tap per sample where its segment reaches the blocker depth.

    Args:
        segments: N points' segments; blocker_depth: (N, 1) the depth the taps are taken at;
        jitter: column and row offsets (1, S) in texels.

    Returns:
        (N, S) each: the tap's distance from the point along the segment; the occluder depth
        stored in its texel, >= the dtype's largest value where none or where it is the
        receiver's own plane (`_receiver_plane`); whether that surface lies in front of the
        receiver's depth; whether the tap is blocked: the surface lies in front of the tap, or
        behind it by less than `TAP_TOLERANCE_FRACTION` of the tap's distance to the receiver's
        depth; and whether it is crossed: blocked, and not in front by more than that either
        (the segment meets the surface at the tap). Comparisons carry the slope-scaled bias of
        the module doc.
    """
    along = ((segments.receiver_depth - blocker_depth) / segments.span).clamp(0.0, 1.0) * segments.reach
    x, y, z = (p + along * d for p, d in zip(segments.point, segments.direction, strict=True))
    look = depth_map.sample(x, y, z, jitter)
    stored = _receiver_plane(depth_map, look, segments)
    bias = depth_map.footprint(torch.minimum(stored, segments.receiver_depth)) * BEHIND_TEXELS + look.slope
    in_front = stored < segments.receiver_depth - bias
    tolerance = (segments.receiver_depth - look.depth).clamp_min(0.0) * TAP_TOLERANCE_FRACTION + bias
    blocked = in_front & (stored < look.depth + tolerance)
    return along, stored, in_front, blocked, blocked & (stored > look.depth - tolerance)


def _receiver_plane(depth_map: DepthMap, look: MapSample, segments: _Segments) -> torch.Tensor:
    """Stored depths (N, S) raised to the dtype's largest value where they are the receiver's own plane.

    The test of `_stored_without_receiver` (the plane's depth along the texel-centre ray equals
    the stored depth within one footprint times 1 + tan of the incidence, tan capped at
    `MAX_RECEIVER_SLOPE`), multiplied through by |cos| so that no division or `where` (each
    several times an add on the CPU) is needed.
    """
    cos, numerator = depth_map.texel_plane(look, segments.normal, segments.point_normal)
    abs_cos = cos.abs()
    sin = (1.0 - cos * cos).clamp_min(0.0).sqrt()
    # |cos| (1 + tan) with tan = sin / max(|cos|, 1 / MAX_RECEIVER_SLOPE).
    slack = abs_cos + sin * (abs_cos * MAX_RECEIVER_SLOPE).clamp_max(1.0)
    # NaN where nothing was stored (inf x 0): not the receiver, and the depth stays inf.
    own = (look.stored * cos - numerator).abs() <= depth_map.footprint(look.stored) * slack * RECEIVER_PLANE_TEXELS
    return torch.maximum(look.stored, own.to(look.stored.dtype) * torch.finfo(look.stored.dtype).max)


def _percentage_closer(
    depth_map: DepthMap, points: torch.Tensor, normals: torch.Tensor, directions: torch.Tensor, reach: torch.Tensor
) -> torch.Tensor:
    """Distance (N, S) to the occluder of each sample's segment by one PCF tap per sample, inf if none.

    Percentage-closer soft shadows (Fernando 2005) with the light's own samples as the filter
    taps: a sample's segment p -> p + reach d crosses a blocker at map depth z where it reaches
    that depth, so its tap is the map texel of that point; the tap is blocked when the texel's
    surface is there (or in front). Blocker depths come from a first tap per sample: at the
    depth stored in the receiver's own texel when the centre's ray to it is blocked (those taps
    are final), else at `SEARCH_DEPTH_FRACTION` of the receiver's depth (wider than any blocker
    nearer the receiver needs). The first taps that see a surface in front of the receiver are
    its blockers; points with none are lit by every sample and take no more taps. The others
    take a tap at their deepest blocker that counts only where the segment crosses a surface
    there (the contact shadow at the foot of a box, which the centre's ray passes above), and
    the points the centre lights one at their blockers' mean depth: a sample is blocked when any
    of its taps is. Three map reads per sample at most, each about 25 elementwise operations.

    Arguments as `_march`. The reported distance is the nearest blocked tap's distance from the point.
    """
    num_points, num_samples = reach.shape
    if num_points == 0:
        return torch.full_like(reach, torch.inf)
    tiny = torch.finfo(reach.dtype).tiny
    jitter = tuple(t.unsqueeze(0).contiguous() for t in _sample_jitter(num_samples, points).unbind(-1))
    px, py, pz = (t.unsqueeze(-1).contiguous() for t in points.unbind(-1))
    dx, dy, dz = (t.contiguous() for t in directions.unbind(-1))
    point, direction = (px, py, pz), (dx, dy, dz)
    normal = normals.unsqueeze(1)
    end_depth = depth_map.depth_of(*(p + reach * d for p, d in zip(point, direction, strict=True)))
    centre = depth_map.sample(px, py, pz)
    segments = _Segments(
        point,
        normal,
        (points * normals).sum(-1, keepdim=True),
        direction,
        reach,
        centre.depth,
        (centre.depth - end_depth).clamp_min(tiny),
    )
    stored = _receiver_plane(depth_map, centre, segments)
    shadowed = (
        centre.depth - stored > depth_map.footprint(torch.minimum(stored, centre.depth)) * BEHIND_TEXELS + centre.slope
    )
    search_depth = torch.where(shadowed, stored, SEARCH_DEPTH_FRACTION * centre.depth)
    along, taps, in_front, blocked, _ = _tap(depth_map, segments, search_depth, jitter)
    # Distances where blocked, inf elsewhere (a division by the 0/1 mask: `where` costs ~10 adds on the CPU).
    found = along.clamp_min(tiny) / (blocked & shadowed).to(along.dtype)
    candidates = in_front.any(-1)
    # Taps in front are nearer than the receiver: the minimum keeps the others finite (x 0).
    blockers = torch.minimum(taps, centre.depth) * in_front.to(taps.dtype)
    # Every point with blockers: a tap at the deepest, blocked only where it crosses a surface.
    again = torch.nonzero(candidates).squeeze(-1)
    if again.numel():
        along, _, _, _, crossing = _tap(depth_map, segments.rows(again), blockers[again].amax(-1, keepdim=True), jitter)
        found[again] = torch.minimum(found[again], along.clamp_min(tiny) / crossing.to(along.dtype))
    # Points the centre lights, with blockers: a tap at their mean depth.
    again = torch.nonzero(candidates & ~shadowed.squeeze(-1)).squeeze(-1)
    if again.numel():
        depth = blockers[again].sum(-1, keepdim=True) / in_front[again].sum(-1, keepdim=True)
        along, _, _, blocked, _ = _tap(depth_map, segments.rows(again), depth, jitter)
        found[again] = torch.minimum(found[again], along.clamp_min(tiny) / blocked.to(along.dtype))
    return found
