"""Depth maps seen from a light: pinhole faces (cube maps, spot maps) and an orthographic map.

A map is F faces of R x R texels; texel (row, col) of face f is the ray through its centre, and
the map stores the distance along that ray to the nearest occluder (`raster.rasterise_depth`).
Face-local image coordinates (u, v) lie in [-1, 1]; u runs along the columns, v along the rows,
and texel centres sit at u = (col + 0.5) * 2 / R - 1.

    PinholeMaps  rays from one centre. A face's frame `face_from_world` (rows: right, up,
                 forward) and `tan_half_fov`: (u, v) = (x, y) / (z tan_half_fov) in face-local
                 coordinates. One face along a spot light's axis makes a perspective map; depth
                 is the distance to the centre.
    CubeMap      six axis-aligned PinholeMaps faces with tan_half_fov = 1.
    OrthoMap     parallel rays along `forward` (a distant light's -direction) starting on a plane
                 above every occluder: a square window of that plane. Depth is the distance below
                 the plane.

`lookup` turns query points into the texel they fall in, their own depth along the map's rays,
the texel-centre ray (for the receiver-plane test of `shadow_maps`) and the texel's depth slope
(for the slope-scaled bias). Biases are measured in texel footprints (`footprint`), never in a
world epsilon.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from relight_torch.visibility.raster import rasterise_depth

# Near clip of pinhole faces, relative to each triangle's largest face-local coordinate:
# keeps the projection of a triangle passing through the centre finite.
NEAR_CLIP_FRACTION = 1e-6


@dataclass(frozen=True)
class MapLookup:
    """Where query points fall in a depth map (all shapes (...) of the queries).

    Attributes:
        stored: (...) occluder depth of the texel, inf outside the map or where it saw nothing.
        depth: (...) the query's own depth along the map's rays.
        ray_origin: (..., 3) origin of the texel-centre ray.
        ray_direction: (..., 3) unit direction of the texel-centre ray.
        slope: (...) how much the stored depth may change from the texel centre to a point up to
            one texel away (sum over the two image axes of the smaller one-sided difference to a
            neighbour texel, so that a silhouette does not count; 0 for an isolated texel).
    """

    stored: torch.Tensor
    depth: torch.Tensor
    ray_origin: torch.Tensor
    ray_direction: torch.Tensor
    slope: torch.Tensor


class DepthMap:
    """Shared texel arithmetic and lookup; subclasses define the projection.

    Attributes:
        num_faces: F.
        resolution: R, texels per face side.
        face_from_world: (F, 3, 3) rows right, up, forward of each face (world units).
        depth: (F, R, R) stored occluder depth, set by `build`.
        slope: (F, R, R) depth change to a neighbour texel (see `MapLookup.slope`), set by `build`.
    """

    num_faces: int
    resolution: int
    face_from_world: torch.Tensor
    depth: torch.Tensor
    slope: torch.Tensor

    def build(self, corners: torch.Tensor) -> None:
        """Rasterise (T, 3, 3) world triangles into `depth` and derive `slope`."""
        self.depth = rasterise_depth(self, corners)
        self.slope = _axis_slope(self.depth, -1) + _axis_slope(self.depth, -2)

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(face (...) long, uv (..., 2), depth (...), inside (...) bool) of world points (..., 3)."""
        raise NotImplementedError

    def texel_rays(self, face: torch.Tensor, row: torch.Tensor, col: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(origins (..., 3), unit directions (..., 3)) of the rays through texel centres (...)."""
        raise NotImplementedError

    def footprint(self, depth: torch.Tensor) -> torch.Tensor:
        """(...) world size of a texel at depths (...)."""
        raise NotImplementedError

    def texel_centre_uv(self, row: torch.Tensor, col: torch.Tensor) -> torch.Tensor:
        """(..., 2) image coordinates (u, v) of texel centres (...)."""
        return (torch.stack((col, row), dim=-1).to(self.face_from_world.dtype) + 0.5) * (2.0 / self.resolution) - 1.0

    def lookup(self, points: torch.Tensor, jitter: torch.Tensor | None = None) -> MapLookup:
        """The texels world points fall in (nearest texel, optionally jittered).

        Args:
            points: (..., 3) world points (the map's dtype).
            jitter: (..., 2) offsets in texels added before rounding to a texel (PCF taps), or None.

        Returns:
            MapLookup of shape (...).
        """
        face, uv, depth, inside = self.project(points)
        texel = (uv + 1.0) * (0.5 * self.resolution)
        if jitter is not None:
            texel = texel + jitter
        index = torch.floor(texel).clamp(0, self.resolution - 1).long()
        col, row = index[..., 0], index[..., 1]
        flat = (face * self.resolution + row) * self.resolution + col
        stored = torch.where(inside, _take(self.depth, flat), torch.inf)
        origin, direction = self.texel_rays(face, row, col)
        return MapLookup(stored, depth, origin, direction, _take(self.slope, flat))


def _take(table: torch.Tensor, flat: torch.Tensor) -> torch.Tensor:
    """Rows of a (F, R, R, ...) table at flat texel indices (...): (..., ...) (index_select is
    several times faster than indexing with three index tensors)."""
    rows = table.reshape(-1, *table.shape[3:]).index_select(0, flat.reshape(-1))
    return rows.reshape(*flat.shape, *table.shape[3:])


def _axis_slope(depth: torch.Tensor, dim: int) -> torch.Tensor:
    """(F, R, R) smaller absolute one-sided depth difference along `dim`; 0 where both are undefined."""
    step = torch.diff(depth, dim=dim).abs()
    step = torch.where(torch.isnan(step), torch.full_like(step, torch.inf), step)
    pad_shape = list(step.shape)
    pad_shape[dim] = 1
    pad = torch.full(pad_shape, torch.inf, device=depth.device, dtype=depth.dtype)
    smaller = torch.minimum(torch.cat((pad, step), dim=dim), torch.cat((step, pad), dim=dim))
    return torch.where(torch.isfinite(smaller), smaller, torch.zeros_like(smaller))


def _texel_range(low: torch.Tensor, high: torch.Tensor, resolution: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(start, count) long of the texel centres whose coordinate lies in [low, high] (...)."""
    start = torch.ceil((low + 1.0) * (0.5 * resolution) - 0.5).clamp(0, resolution)
    stop = torch.floor((high + 1.0) * (0.5 * resolution) - 0.5).clamp(-1, resolution - 1)
    return start.long(), (stop - start + 1).clamp_min(0).long()


def _bounds_from_uv(uv_low: torch.Tensor, uv_high: torch.Tensor, resolution: int) -> torch.Tensor:
    """(..., 4) long texel bounds (col_start, row_start, num_cols, num_rows) of uv boxes (..., 2)."""
    col_start, num_cols = _texel_range(uv_low[..., 0], uv_high[..., 0], resolution)
    row_start, num_rows = _texel_range(uv_low[..., 1], uv_high[..., 1], resolution)
    return torch.stack((col_start, row_start, num_cols, num_rows), dim=-1)


class PinholeMaps(DepthMap):
    """Faces of rays from one centre; with one face, a spot light's perspective map.

    Args:
        centre: (3,) world position of the light.
        face_from_world: (F, 3, 3) orthonormal rows (right, up, forward) per face.
        tan_half_fov: tangent of each face's half field of view (1 for a cube map).
        resolution: texels per face side.
        directions: (F, R, R, 3) `texel_directions` of an identical map (same frames, field of
            view, resolution, dtype), to share rather than recompute; None computes them.

    Attributes:
        directions: (F, R, R, 3) unit world direction of every texel-centre ray (12 bytes a texel
            in float32: computed once rather than at every lookup, which it made 2x slower).
    """

    def __init__(self, centre: torch.Tensor, face_from_world: torch.Tensor, tan_half_fov: float, resolution: int,
                 directions: torch.Tensor | None = None):
        self.centre = centre
        self.face_from_world = face_from_world
        self.num_faces = face_from_world.shape[0]
        self.tan_half_fov = tan_half_fov
        self.resolution = resolution
        self.directions = self.texel_directions() if directions is None else directions

    def texel_directions(self) -> torch.Tensor:
        """(F, R, R, 3) unit world direction of every texel-centre ray (see `directions`)."""
        index = torch.arange(self.resolution, device=self.centre.device)
        row, col = torch.meshgrid(index, index, indexing="ij")
        uv = self.texel_centre_uv(row, col) * self.tan_half_fov
        frame = self.face_from_world[:, None, None]
        return torch.nn.functional.normalize(
            uv[..., 0:1] * frame[..., 0, :] + uv[..., 1:2] * frame[..., 1, :] + frame[..., 2, :], dim=-1)

    def affine_rays(self):
        """Origins: the centre; unnormalised directions: forward + u tan right + v tan up (see `RasterTarget`)."""
        frame = self.face_from_world
        origins = torch.zeros_like(frame)
        origins[:, 0] = self.centre
        return origins, torch.stack((frame[:, 2], self.tan_half_fov * frame[:, 0], self.tan_half_fov * frame[:, 1]), 1)

    def face_local(self, offset: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(face (...) long, face-local coordinates (..., 3)) of world offsets from the centre (..., 3).

        The face is the only one (a spot light's map)."""
        face = torch.zeros(offset.shape[:-1], dtype=torch.long, device=offset.device)
        return face, offset @ self.face_from_world[0].T

    def project(self, points):
        offset = points - self.centre
        face, local = self.face_local(offset)
        z = local[..., 2]
        positive = z > 0
        safe_z = torch.where(positive, z, torch.ones_like(z))
        uv = local[..., :2] / (safe_z * self.tan_half_fov).unsqueeze(-1)
        inside = positive & (uv.abs() <= 1.0).all(dim=-1)
        return face, uv, offset.norm(dim=-1), inside

    def texel_rays(self, face, row, col):
        direction = _take(self.directions, (face * self.resolution + row) * self.resolution + col)
        return self.centre.expand_as(direction), direction

    def footprint(self, depth):
        return depth * (2.0 * self.tan_half_fov / self.resolution)

    def texel_bounds(self, corners):
        """(F, T, 4) texel bounds of each triangle's part in front of each face (near-clipped)."""
        local = torch.einsum("tck,fjk->ftcj", corners - self.centre, self.face_from_world)
        near = NEAR_CLIP_FRACTION * local.abs().amax(dim=(-2, -1), keepdim=True)
        following = local.roll(-1, dims=-2)
        # Points of the clipped polygon: corners in front of the near plane and edge crossings of it.
        above = local[..., 2:3] - near
        above_next = following[..., 2:3] - near
        crosses = (above * above_next) < 0
        fraction = above / torch.where(crosses, above - above_next, torch.ones_like(above))
        crossing = local + fraction * (following - local)
        points = torch.cat((local, crossing), dim=-2)
        valid = torch.cat((above > 0, crosses), dim=-2)
        z = torch.where(valid, points[..., 2:3], torch.ones_like(points[..., 2:3])).clamp_min(near)
        uv = points[..., :2] / (z * self.tan_half_fov)
        low = torch.where(valid, uv, torch.full_like(uv, torch.inf)).amin(dim=-2).clamp(-1.0, 1.0)
        high = torch.where(valid, uv, torch.full_like(uv, -torch.inf)).amax(dim=-2).clamp(-1.0, 1.0)
        # A triangle wholly behind the near plane has low = 1 and high = -1: no texels.
        return _bounds_from_uv(low, high, self.resolution)


class CubeMap(PinholeMaps):
    """Six 90-degree faces looking along +X, -X, +Y, -Y, +Z, -Z (face = 2 axis + [negative]).

    Args:
        centre: (3,) world position of the light.
        resolution: texels per face side.
        directions: as `PinholeMaps` (a cube map's do not depend on its centre).
    """

    def __init__(self, centre: torch.Tensor, resolution: int, directions: torch.Tensor | None = None):
        eye = torch.eye(3, device=centre.device, dtype=centre.dtype)
        faces = []
        for axis in range(3):
            for sign in (1.0, -1.0):
                forward = sign * eye[axis]
                right = eye[(axis + 1) % 3]
                faces.append(torch.stack((right, torch.linalg.cross(forward, right), forward)))
        super().__init__(centre, torch.stack(faces), 1.0, resolution, directions)

    def face_local(self, offset):
        """The face of the dominant axis a (elementwise: an argmax over the faces' z was 10x slower);
        its frame is (e_{a+1}, s e_{a+2}, s e_a) with s the sign, so its coordinates are a signed
        permutation of the offset (a (3, 3) product per face and a gather were 3x slower)."""
        size = offset.abs()
        x_major = (size[..., 0] >= size[..., 1]) & (size[..., 0] >= size[..., 2])
        axis = torch.where(x_major, 0, torch.where(size[..., 1] >= size[..., 2], 1, 2))
        permuted = torch.gather(offset, -1, torch.stack(((axis + 1) % 3, (axis + 2) % 3, axis), dim=-1))
        negative = permuted[..., 2] < 0
        sign = torch.where(negative, -1.0, 1.0).to(offset.dtype)
        local = torch.stack((permuted[..., 0], sign * permuted[..., 1], sign * permuted[..., 2]), dim=-1)
        return 2 * axis + negative.long(), local


class OrthoMap(DepthMap):
    """Parallel rays along `forward` through a square window of a plane above the occluders.

    Args:
        face_from_world: (3, 3) orthonormal rows (right, up, forward).
        window_centre: (3,) world centre of the window, on the starting plane.
        half_size: half the window's side (world units).
        resolution: texels per side.
    """

    def __init__(self, face_from_world: torch.Tensor, window_centre: torch.Tensor, half_size: float,
                 resolution: int):
        self.face_from_world = face_from_world.unsqueeze(0)
        self.window_centre = window_centre
        self.half_size = half_size
        self.num_faces = 1
        self.resolution = resolution

    def project(self, points):
        local = (points - self.window_centre) @ self.face_from_world[0].T
        uv = local[..., :2] / self.half_size
        face = torch.zeros(uv.shape[:-1], dtype=torch.long, device=uv.device)
        return face, uv, local[..., 2], (uv.abs() <= 1.0).all(dim=-1)

    def texel_rays(self, face, row, col):
        uv = self.texel_centre_uv(row, col) * self.half_size
        frame = self.face_from_world[0]
        origin = self.window_centre + uv[..., 0:1] * frame[0] + uv[..., 1:2] * frame[1]
        return origin, frame[2].expand_as(origin)

    def affine_rays(self):
        """Origins: the window's centre + u h right + v h up; directions: forward (see `RasterTarget`)."""
        frame = self.face_from_world[0]
        origins = torch.stack((self.window_centre, self.half_size * frame[0], self.half_size * frame[1]))
        directions = torch.zeros_like(frame)
        directions[0] = frame[2]
        return origins.unsqueeze(0), directions.unsqueeze(0)

    def footprint(self, depth):
        return torch.full_like(depth, 2.0 * self.half_size / self.resolution)

    def texel_bounds(self, corners):
        uv = ((corners - self.window_centre) @ self.face_from_world[0, :2].T) / self.half_size
        return _bounds_from_uv(uv.amin(dim=-2), uv.amax(dim=-2), self.resolution).unsqueeze(0)
