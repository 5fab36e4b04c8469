"""The correspondence map (Kim et al. 2009, eq. 5): which caching camera's sample shades each point.

For a visible point p with unit normal n (facing the new camera), camera i at distance d_i in unit
direction u_i scores

    v_i(p) (n . u_i) / (d_i^2 a_i^2)

and the point takes the sample of the best-scoring camera at the pixel p projects to. a_i is the
angle one pixel of camera i subtends: the paper's score (n . u_i) / d_i^2 is the surface's
solid-angle density seen by camera i, which ranks cameras of one resolution; divided by a_i^2 it
is the number of camera i's pixels per unit area of the surface, which also ranks a 64-pixel
camera near a surface against a 256-pixel one further away (on the set scene the former won the
floor next to the viewer, and its coarse samples of a sun patch's hard edges cost 7 dB there). Visibility
v_i is a depth test against camera i's cached depth at that pixel: p is seen when its depth along
the camera's axis is within a tolerance of the cached one. The tolerance is what a surface tilted
by theta away from the camera spans across one pixel, depth x pixel_angle x (1 + 2 tan theta),
(tan clamped at 20), so that grazing surfaces are not rejected for their own slope, plus 0.1 % of
the depth for rounding. Cameras on the point's back side (n . u_i <= 0) never score. Near edges
and corners that tolerance also admits the neighbouring surface's sample, so the cached sample
must moreover be the same surface: the same object, with a geometric normal within
`SAME_SURFACE_COS` of the point's (the paper's "artifacts at surface boundaries", removed).

`correspondence_map` is the vectorised map (every camera's score bound at once, then rounds
testing each point against its best remaining camera); the tests compare it with a loop over
points and cameras written from the formula (tests/test_multiview_parts.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from relight_torch.multiview.views import SAME_SURFACE_COS, CachingViews, take_rows, take_small

MAX_SLOPE = 20.0
RELATIVE_DEPTH_TOLERANCE = 1e-3


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

    def to(self, device: torch.device | str) -> ViewPoints:
        return ViewPoints(
            self.image_size,
            self.pixel_index.to(device),
            self.position.to(device),
            self.geometric_normal.to(device),
            self.object_id.to(device),
            self.depth.to(device),
            self.camera_position.to(device),
            None if self.shading_normal is None else self.shading_normal.to(device),
        )


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
    """(...,) bool: cached samples (`CachingViews.surface_table` columns, (4, ...)) of the same surface
    as points of `object_id` (...,) float32 with unit geometric normals (..., 3)."""
    cos = surface[1] * normal[..., 0] + surface[2] * normal[..., 1] + surface[3] * normal[..., 2]
    return (surface[0] == object_id) & (cos > SAME_SURFACE_COS)


def _depth_tolerance(depth, pixel_angle, cos):
    slope = torch.clamp(
        torch.sqrt(torch.clamp(1.0 - cos * cos, min=0.0)) / torch.clamp(cos, min=1.0 / MAX_SLOPE), max=MAX_SLOPE
    )
    return depth * (pixel_angle * (1.0 + 2.0 * slope) + RELATIVE_DEPTH_TOLERANCE)


def correspondence_map(
    views: CachingViews, position: torch.Tensor, normal: torch.Tensor, object_id: torch.Tensor
) -> Correspondence:
    """Eq. 5 for every point, all cameras at once.

    The score without visibility, (n . u_i) / d_i^2, bounds each camera's score from above, so
    a point's best camera is the first one, in decreasing bound, that passes the visibility test:
    the bounds of all (N, J) pairs come from matrix products, then each round tests every pending
    point against its best remaining camera (one gather of that camera's projection per point)
    and keeps the points it failed for. Most points are done in the first round or two; the
    rounds never exceed J. The J columns are the single cameras and the omni-directional ones
    (`CachingViews.cubes`): a point can only be seen by the face of a cube its direction from the
    centre falls in, so a cube is one column, scored through that face (its other faces would
    fail the test, at the price of a round each).

    Args:
        views: the caching cameras (on the points' device).
        position: (N, 3) float32 world points.
        normal: (N, 3) unit geometric normals at the points, facing the viewer.
        object_id: (N,) object of each point.
    """
    device = position.device
    num_points = position.shape[0]
    best_score = torch.zeros(num_points, dtype=torch.float32, device=device)
    best_view = torch.full((num_points,), -1, dtype=torch.int64, device=device)
    best_row = torch.full((num_points,), -1, dtype=torch.int64, device=device)
    best_pixel = torch.full((num_points, 2), torch.nan, dtype=torch.float32, device=device)
    if num_points == 0 or views.num_views == 0:
        return Correspondence(best_view, best_row, best_score, best_pixel)
    bound, faces = _score_bounds(views, position, normal)  # (N, J), (C, N)
    object_id = object_id.to(torch.float32)
    pending = None  # every point
    for _ in range(bound.shape[1]):
        rows = bound if pending is None else bound.index_select(0, pending)
        value, column = rows.max(1)
        live = torch.nonzero(value > 0).squeeze(-1)
        pending = live if pending is None else pending.index_select(0, live)
        if pending.numel() == 0:
            break
        column = column.index_select(0, live)
        camera = _column_camera(views, faces, column, pending)
        pixel, row, score = _visible_sample(
            views,
            camera,
            position.index_select(0, pending),
            normal.index_select(0, pending),
            object_id.index_select(0, pending),
        )
        seen = row >= 0
        found = torch.nonzero(seen).squeeze(-1)
        done = pending.index_select(0, found)
        best_score.index_copy_(0, done, score.index_select(0, found))
        best_view.index_copy_(0, done, camera.index_select(0, found))
        best_row.index_copy_(0, done, row.index_select(0, found))
        best_pixel.index_copy_(0, done, pixel.index_select(0, found))
        failed = torch.nonzero(~seen).squeeze(-1)
        pending = pending.index_select(0, failed)
        bound.view(-1).index_fill_(0, pending * bound.shape[1] + column.index_select(0, failed), 0.0)
    return Correspondence(best_view, best_row, best_score, best_pixel)


def _column_camera(
    views: CachingViews, faces: torch.Tensor, column: torch.Tensor, points: torch.Tensor
) -> torch.Tensor:
    """(P,) int64 the camera of bound columns `column` (P,) at `points` (P,): a single camera's own,
    a cube's face the point lies in (`faces`, (C, N), from `_score_bounds`)."""
    num_singles = views.singles.shape[0]
    if faces.shape[0] == 0:
        return views.singles.index_select(0, column)
    face = faces.view(-1).index_select(0, (column - num_singles).clamp_(min=0) * faces.shape[1] + points)
    if num_singles == 0:
        return face
    return torch.where(column < num_singles, views.singles.index_select(0, column.clamp(max=num_singles - 1)), face)


def _score_bounds(
    views: CachingViews, position: torch.Tensor, normal: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, J) float32 (n . u_j) / (d_j^2 a_j^2) of every point and bound column, and (C, N) int64 the
    camera of the face of each cube each point lies in (-1: a dropped face).

    The J = S + C columns are the S single cameras (`CachingViews.singles`), 0 where the point is
    outside the cone around the camera's frustum (`CachingViews.axes`), then the C cubes
    (`CachingViews.cubes`), whose a_j is that face's (0 for a dropped one). 0 where the camera is
    behind the point's surface. From matrix products about the points' mean (float32 rounding of
    the squared distance, relative to the scene's extent squared: the order of near-ties only)."""
    singles, cubes = views.singles, views.cubes
    num_singles = singles.shape[0]
    dtype = position.dtype
    origin = position.mean(0)
    members = torch.cat([singles, cubes.amax(1)])  # a camera of each column (a cube's: any face)
    points, centres = position - origin, views.centres.index_select(1, members).T.to(dtype) - origin
    facing = torch.addmm(-(normal * points).sum(-1, keepdim=True), normal, centres.T)  # n.(c - p)
    squared = torch.addmm(
        (points * points).sum(-1, keepdim=True) + (centres * centres).sum(-1), points, centres.T, alpha=-2.0
    ).clamp_(min=1e-30)
    inverse = squared.rsqrt_()
    facing.clamp_(min=0.0).mul_(inverse).mul_(inverse).mul_(inverse)
    angle = views.pixel_angle.to(dtype)
    if num_singles:
        forward, cone = views.axes[:3].index_select(1, singles).T.to(dtype), views.axes[3].index_select(0, singles)
        ahead = torch.addmm(-(forward * centres[:num_singles]).sum(-1), points, forward.T)  # f.(p - c)
        facing[:, :num_singles].mul_(angle.index_select(0, singles) ** -2).mul_(
            ahead.mul_(inverse[:, :num_singles]) > cone.to(dtype)
        )
    faces = []
    for c in range(cubes.shape[0]):
        direction = points - centres[num_singles + c]
        x, y, z = direction.abs().unbind(-1)
        axis = torch.where((x >= y) & (x >= z), 0, torch.where(y >= z, 1, 2))
        face = 2 * axis + (direction.gather(1, axis[:, None])[:, 0] < 0)
        camera = cubes[c].index_select(0, face)
        facing[:, num_singles + c].mul_(torch.where(camera >= 0, angle.index_select(0, camera.clamp(min=0)) ** -2, 0.0))
        faces.append(camera)
    return facing, torch.stack(faces) if faces else torch.zeros(
        (0, position.shape[0]), dtype=torch.int64, device=position.device
    )


def _visible_sample(
    views: CachingViews, camera: torch.Tensor, position: torch.Tensor, normal: torch.Tensor, object_id: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each point (P, 3) seen by its own `camera` (P,): its continuous (column, row) (P, 2), the
    cached sample's pool row (-1 where the depth or same-surface test fails) and eq. 5's score (P,)."""
    p = take_small(views.projection, camera)  # (19, P)
    x, y, z = position[:, 0], position[:, 1], position[:, 2]
    local_x, local_y, local_z = (p[4 * i] * x + p[4 * i + 1] * y + p[4 * i + 2] * z + p[4 * i + 3] for i in range(3))
    depth = -local_z
    safe = torch.where(depth > 0, depth, torch.ones_like(depth))
    focal, width, height = p[12], p[17], p[18]
    column = ((focal * local_x / safe - p[15]) / p[13] + 0.5) * width
    line = (0.5 - (focal * local_y / safe - p[16]) / p[14]) * height
    column_index, line_index = torch.floor(column), torch.floor(line)
    inside = (depth > 0) & (column_index >= 0) & (column_index < width) & (line_index >= 0) & (line_index < height)
    flat = torch.where(inside, line_index * width + column_index, torch.zeros_like(column)).long()
    flat += views.image_offsets.index_select(0, camera)
    centre = take_small(views.centres, camera)
    to_x, to_y, to_z = centre[0] - x, centre[1] - y, centre[2] - z
    distance_squared = to_x * to_x + to_y * to_y + to_z * to_z
    cos = (normal[:, 0] * to_x + normal[:, 1] * to_y + normal[:, 2] * to_z) * torch.rsqrt(
        torch.clamp(distance_squared, min=1e-30)
    )
    angle = views.pixel_angle.index_select(0, camera)
    tolerance = _depth_tolerance(depth, angle, cos)
    seen = inside & (cos > 0) & ((depth - views.depth.index_select(0, flat)).abs() <= tolerance)
    sample = torch.where(seen, views.pool_row.index_select(0, flat), torch.zeros_like(flat))
    seen &= same_surface(take_rows(views.surface_table, sample), object_id, normal)
    return (
        torch.stack((column, line), -1),
        torch.where(seen, sample, torch.full_like(sample, -1)),
        cos / distance_squared / (angle * angle),
    )
