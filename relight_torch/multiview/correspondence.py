"""The correspondence map (Kim et al. 2009, eq. 5): which caching camera's sample shades each point.

For a visible point p with unit normal n (facing the new camera), camera i at distance d_i in unit
direction u_i scores

    v_i(p) (n . u_i) / d_i^2

and the point takes the sample of the best-scoring camera at the pixel p projects to. Visibility
v_i is a depth test against camera i's cached depth at that pixel: p is seen when its depth along
the camera's axis is within a tolerance of the cached one. The tolerance is what a surface tilted
by theta away from the camera spans across one pixel, depth x pixel_angle x (1 + 2 tan theta),
(tan clamped at 20), so that grazing surfaces are not rejected for their own slope, plus 0.1 % of
the depth for rounding. Cameras on the point's back side (n . u_i <= 0) never score. Near edges
and corners that tolerance also admits the neighbouring surface's sample, so the cached sample
must moreover be the same surface: the same object, with a geometric normal within
`SAME_SURFACE_COS` of the point's (the paper's "artifacts at surface boundaries", removed).

`correspondence_map` is the vectorised map (a loop over the K cameras, each over the points
inside its frustum);
`correspondence_map_reference` is its slow twin, a loop over points and cameras written from the
formula, used by the tests only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from relight_torch.multiview.views import CachingViews, camera_column, world_from_camera

MAX_SLOPE = 20.0
RELATIVE_DEPTH_TOLERANCE = 1e-3
SAME_SURFACE_COS = 0.7


@dataclass(frozen=True)
class ViewPoints:
    """The surfaces a new view sees: one sample per covered sub-sample of its (H, W) image.

    Attributes:
        image_size: (H, W) of the sub-sample image (the image times the supersampling).
        pixel_index: (N,) int64 flat index row * W + col of each covered sub-sample.
        position: (N, 3) float32 world-space hit points.
        geometric_normal: (N, 3) float32 unit normals, facing the new camera.
        object_id: (N,) int64 object of each hit (holes are filled from the same object only).
        depth: (N,) float32 distance along the new camera's viewing axis.
        camera_position: (3,) float32 world position of the new camera.
        shading_normal: (N, 3) float32 unit smooth normals (interpolated from the mesh's, on the
            camera's side), or None.
    """

    image_size: tuple[int, int]
    pixel_index: torch.Tensor
    position: torch.Tensor
    geometric_normal: torch.Tensor
    object_id: torch.Tensor
    depth: torch.Tensor
    camera_position: torch.Tensor
    shading_normal: torch.Tensor | None = None

    @property
    def num_points(self) -> int:
        return int(self.pixel_index.shape[0])

    def to(self, device: torch.device | str) -> "ViewPoints":
        return ViewPoints(self.image_size, self.pixel_index.to(device), self.position.to(device),
                          self.geometric_normal.to(device), self.object_id.to(device), self.depth.to(device),
                          self.camera_position.to(device),
                          None if self.shading_normal is None else self.shading_normal.to(device))


@dataclass(frozen=True)
class Correspondence:
    """Per point of a `ViewPoints`: the chosen camera and sample (N,) each.

    Attributes:
        view: int64 caching camera index, -1 where no camera sees the point (a hole).
        pool_row: int64 row of the chosen sample in `CachingViews.pool`, -1 for holes.
        score: float32 the winning eq. 5 score (0 for holes).
        pixel: (N, 2) float32 continuous (column, row) of the point in the chosen camera's image
            (NaN for holes), or None.
    """

    view: torch.Tensor
    pool_row: torch.Tensor
    score: torch.Tensor
    pixel: torch.Tensor | None = None

    @property
    def covered(self) -> torch.Tensor:
        return self.pool_row >= 0


def same_surface(surface: torch.Tensor, object_id: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """(...,) bool: cached samples (`CachingViews.surface_table` rows, (..., 4)) of the same surface as
    points of `object_id` (...,) float32 with unit geometric normals (..., 3)."""
    cos = surface[..., 1] * normal[..., 0] + surface[..., 2] * normal[..., 1] + surface[..., 3] * normal[..., 2]
    return (surface[..., 0] == object_id) & (cos > SAME_SURFACE_COS)


def _depth_tolerance(depth, pixel_angle, cos):
    slope = torch.clamp(torch.sqrt(torch.clamp(1.0 - cos * cos, min=0.0)) / torch.clamp(cos, min=1.0 / MAX_SLOPE),
                        max=MAX_SLOPE)
    return depth * (pixel_angle * (1.0 + 2.0 * slope) + RELATIVE_DEPTH_TOLERANCE)


def correspondence_map(views: CachingViews, position: torch.Tensor, normal: torch.Tensor,
                       object_id: torch.Tensor) -> Correspondence:
    """Eq. 5 for every point.

    Args:
        views: the caching cameras (on the points' device).
        position: (N, 3) float32 world points.
        normal: (N, 3) unit geometric normals at the points, facing the viewer.
        object_id: (N,) object of each point.
    """
    object_id = object_id.to(torch.float32)
    num_points = position.shape[0]
    best_score = torch.zeros(num_points, dtype=torch.float32, device=position.device)
    best_view = torch.full((num_points,), -1, dtype=torch.int64, device=position.device)
    best_row = torch.full((num_points,), -1, dtype=torch.int64, device=position.device)
    best_pixel = torch.full((num_points, 2), torch.nan, dtype=torch.float32, device=position.device)
    for k in range(views.num_views):
        pixels, depth = views.project(k, position)
        height, width = (int(v) for v in views.sizes[k])
        column, row = torch.floor(pixels[:, 0]), torch.floor(pixels[:, 1])
        # The rest only for the points inside the frustum (a cube face holds about a sixth).
        index = torch.nonzero((depth > 0) & (column >= 0) & (column < width) & (row >= 0) & (row < height)).squeeze(-1)
        point, point_normal, depth = position[index], normal[index], depth[index]
        to_camera = views.camera_position(k) - point
        distance_squared = (to_camera * to_camera).sum(-1)
        cos = (point_normal * to_camera).sum(-1) * torch.rsqrt(torch.clamp(distance_squared, min=1e-30))
        flat = (row[index] * width + column[index]).long() + views.image_offsets[k]
        sample = views.pool_row[flat]
        seen = (cos > 0) & ((depth - views.depth[flat]).abs() <= _depth_tolerance(depth, views.pixel_angle[k], cos))
        sample = torch.where(seen, sample, torch.zeros_like(sample))
        seen &= same_surface(views.surface_table[sample], object_id[index], point_normal)
        score = torch.where(seen, cos / distance_squared, torch.zeros_like(cos))
        better = score > best_score[index]
        chosen = index[better]
        best_score[chosen] = score[better]
        best_view[chosen] = k
        best_row[chosen] = sample[better]
        best_pixel[chosen] = pixels[index[better]].float()
    return Correspondence(best_view, best_row, best_score, best_pixel)


def correspondence_map_reference(views: CachingViews, position: np.ndarray, normal: np.ndarray,
                                 object_id: np.ndarray) -> Correspondence:
    """The slow twin of `correspondence_map`: a Python loop over points and cameras (tests only)."""
    table = views.table
    world = world_from_camera(table)
    sizes = views.sizes.cpu().numpy()
    offsets = views.image_offsets.cpu().numpy()
    cached_depth, pool_row = views.depth.cpu().numpy(), views.pool_row.cpu().numpy()
    pool_object, pool_normal = views.pool.object_id.cpu().numpy(), views.pool.geometric_normal.cpu().numpy()
    pixel_angle = views.pixel_angle.cpu().numpy()
    focal, h_ap, v_ap = (camera_column(table, n) for n in ("focalLength", "horizontalAperture", "verticalAperture"))
    h_off, v_off = camera_column(table, "horizontalApertureOffset"), camera_column(table, "verticalApertureOffset")
    view = np.full(len(position), -1, np.int64)
    rows = np.full(len(position), -1, np.int64)
    scores = np.zeros(len(position), np.float32)
    for i, (p, n) in enumerate(zip(np.asarray(position, np.float64), np.asarray(normal, np.float64))):
        for k in range(len(table)):
            centre, axes = world[k][:3, 3], world[k][:3, :3]
            offset = centre - p
            d = np.linalg.norm(offset)
            cos = float(n @ offset / d)
            local = np.linalg.solve(axes, p - centre)
            depth = -local[2]
            if cos <= 0 or depth <= 0:
                continue
            height, width = sizes[k]
            x = ((focal[k] * local[0] / depth - h_off[k]) / h_ap[k] + 0.5) * width
            y = (0.5 - (focal[k] * local[1] / depth - v_off[k]) / v_ap[k]) * height
            if not (0 <= x < width and 0 <= y < height):
                continue
            pixel = offsets[k] + int(np.floor(y)) * width + int(np.floor(x))
            slope = min(np.sqrt(max(1 - cos * cos, 0.0)) / max(cos, 1 / MAX_SLOPE), MAX_SLOPE)
            tolerance = depth * (pixel_angle[k] * (1 + 2 * slope) + RELATIVE_DEPTH_TOLERANCE)
            if abs(depth - cached_depth[pixel]) > tolerance:
                continue
            sample = pool_row[pixel]
            if pool_object[sample] != object_id[i] or float(pool_normal[sample] @ n) <= SAME_SURFACE_COS:
                continue
            score = cos / (d * d)
            if score > scores[i]:
                view[i], rows[i], scores[i] = k, sample, score
    return Correspondence(torch.from_numpy(view), torch.from_numpy(rows), torch.from_numpy(scores))
