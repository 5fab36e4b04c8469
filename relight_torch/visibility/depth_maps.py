"""Depth maps seen from a light: pinhole faces (cube maps, spot maps) and an orthographic map.

A map is F faces of R x R texels; texel (row, col) of face f is the ray through its centre, and
the map stores the distance along that ray to the nearest occluder (`raster.rasterise_depth`).
Face-local image coordinates (u, v) lie in [-1, 1]; u runs along the columns, v along the rows,
and texel centres sit at u = (col + 0.5) * 2 / R - 1.

    PinholeMaps  rays from one centre. A face's frame `face_from_world` (rows: right, up,
                 forward) and `tan_half_fov`: (u, v) = (x, y) / (z tan_half_fov) in face-local
                 coordinates. One face along a spot light's axis makes a perspective map; depth
                 is the distance to the centre.
    CubeMap      six axis-aligned PinholeMaps faces with tan_half_fov = 1; for a one-sided
                 light, only the texels facing its emitting side are rasterised.
    OrthoMap     parallel rays along `forward` (a distant light's -direction) starting on a plane
                 above every occluder: a square window of that plane. Depth is the distance below
                 the plane.

`lookup` turns query points into the texel they fall in, their own depth along the map's rays,
the texel-centre ray (for the receiver-plane test of `shadow_maps`) and the texel's depth slope
(for the slope-scaled bias); `sample` the same with coordinates as separate tensors and without
the ray (`texel_plane` gives what the receiver-plane test needs of it). Biases are measured in
texel footprints (`footprint`), never in a world epsilon.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from relight_torch.visibility.opacity import OpacityTable
from relight_torch.visibility.raster import rasterise_depth

# Near clip of pinhole faces, relative to each triangle's largest face-local coordinate:
# keeps the projection of a triangle passing through the centre finite.
NEAR_CLIP_FRACTION = 1e-6
FRONT_MARGIN_TEXELS = 4
"""Texels a cube map rasterises beyond a one-sided light's emitting half-space on each side: a
lookup's jitter (half a texel) and the depth slope of the texels it reads stay as a full build's."""


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


@dataclass(frozen=True)
class MapSample:
    """The texels query points fall in, without their texel-centre rays (all shapes (...)).

    Attributes:
        stored: occluder depth of the texel, inf outside the map or where it saw nothing.
        depth: the query's own depth along the map's rays.
        slope: the texel's depth slope (see `MapLookup.slope`).
        row, col, flat: int32 the texel's row and column on its face and its flat index.
    """

    stored: torch.Tensor
    depth: torch.Tensor
    slope: torch.Tensor
    row: torch.Tensor
    col: torch.Tensor
    flat: torch.Tensor


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

    def build(self, corners: torch.Tensor, opacity: OpacityTable | None = None) -> None:
        """Rasterise (T, 3, 3) world triangles (with the holes of their `opacity` table) into
        `depth` and derive `slope`."""
        self.depth = rasterise_depth(self, corners, opacity)
        self.slope = _axis_slope(self.depth, -1) + _axis_slope(self.depth, -2)

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(face (...) long, uv (..., 2), depth (...), inside (...) bool) of world points (..., 3)."""
        face, u, v, depth, inside = self.project_components(*points.unbind(-1))
        if inside is None:
            inside = torch.ones_like(depth, dtype=torch.bool)
        return face.long(), torch.stack((u, v), dim=-1), depth, inside

    def project_components(
        self, x: torch.Tensor, y: torch.Tensor, z: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """(face, u, v, depth, inside bool or None when every point is inside), each (...), of
        world points given by their coordinates x, y, z (broadcast to (...)); face holds whole
        numbers (any dtype). Coordinates as separate contiguous tensors: torch's CPU kernels run
        5-20x slower on the strided or reduced last axis of (..., 3), and `where` costs about ten
        adds, so the cube map picks its face with 0/1 masks."""
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

    def texel_plane(
        self, sample: MapSample, normals: torch.Tensor, point_normal: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Where the texel-centre rays of a sample meet planes through points p with unit normals n.

        Args:
            sample: the texels (...) (`sample`).
            normals: (..., 3) n, broadcast against the texels' shape plus 3; point_normal: p.n (...).

        Returns:
            (cos, numerator), each (...): the cosine between each texel's ray and n, and (p - o).n
            for the ray's origin o; the plane lies at depth numerator / cos along the ray.
        """
        raise NotImplementedError

    def depth_of(self, x: torch.Tensor, y: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """(...) depth along the map's rays of world points given by their coordinates (`project`'s depth alone)."""
        raise NotImplementedError

    def texel_bounds(self, corners: torch.Tensor) -> torch.Tensor:
        """(F, T, 4) long texel bounds of (T, 3, 3) world triangles per face (`RasterTarget`)."""
        raise NotImplementedError

    def affine_rays(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Each face's ray origins and directions as affine functions of image coordinates (`RasterTarget`)."""
        raise NotImplementedError

    def lookup(self, points: torch.Tensor, jitter: torch.Tensor | None = None) -> MapLookup:
        """The texels world points fall in (nearest texel, optionally jittered).

        Args:
            points: (..., 3) world points (the map's dtype).
            jitter: (..., 2) offsets in texels added before rounding to a texel (PCF taps), or None.

        Returns:
            MapLookup of shape (...).
        """
        face, u, v, depth, inside = self.project_components(*points.unbind(-1))
        face, row, col, flat = self._texel(face, u, v, None if jitter is None else jitter.unbind(-1))
        stored = _take(self.depth, flat)
        if inside is not None:
            stored = torch.where(inside, stored, torch.inf)
        origin, direction = self.texel_rays(face, row, col)
        return MapLookup(stored, depth, origin, direction, _take(self.slope, flat))

    def sample(
        self, x: torch.Tensor, y: torch.Tensor, z: torch.Tensor, jitter: tuple[torch.Tensor, ...] | None = None
    ) -> MapSample:
        """`lookup` without the texel-centre rays, of world points given by their coordinates
        (broadcast to (...), see `project_components`); `jitter`: column and row offsets in
        texels (broadcast to (...)), or None. MapSample of shape (...)."""
        face, u, v, depth, inside = self.project_components(x, y, z)
        _, row, col, flat = self._texel(face, u, v, jitter)
        stored = _take(self.depth, flat)
        if inside is not None:
            stored = torch.where(inside, stored, torch.inf)
        return MapSample(stored, depth, _take(self.slope, flat), row, col, flat)

    def _texel(
        self, face: torch.Tensor, u: torch.Tensor, v: torch.Tensor, jitter: tuple[torch.Tensor, ...] | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(face, row, col, flat index) int32 (...) of the texel image coordinates (u, v) (...)
        fall in on `face`, after adding the (column, row) `jitter` in texels."""
        half = 0.5 * self.resolution
        col, row = (u + 1.0) * half, (v + 1.0) * half
        if jitter is not None:
            col, row = col + jitter[0], row + jitter[1]
        col, row = (torch.floor(t).clamp(0, self.resolution - 1).to(torch.int32) for t in (col, row))
        face = face.to(torch.int32)
        return face, row, col, (face * self.resolution + row) * self.resolution + col


def _take(table: torch.Tensor, flat: torch.Tensor) -> torch.Tensor:
    """Rows of a (F, R, R, ...) table at flat texel indices (...): (..., ...) (index_select is
    several times faster than indexing with three index tensors)."""
    rows = table.reshape(-1, *table.shape[3:]).index_select(0, flat.reshape(-1))
    return rows.reshape(*flat.shape, *table.shape[3:])


def _axis_slope(depth: torch.Tensor, dim: int) -> torch.Tensor:
    """(F, R, R) smaller absolute one-sided depth difference along `dim`; 0 where both are undefined."""
    step = torch.diff(depth, dim=dim).abs()  # NaN between two empty texels, inf next to one
    size = depth.shape[dim]
    smaller = torch.empty_like(depth)
    # fmin skips NaN (no defined difference on that side); the edge texels have one side only.
    torch.fmin(step.narrow(dim, 0, size - 2), step.narrow(dim, 1, size - 2), out=smaller.narrow(dim, 1, size - 2))
    smaller.narrow(dim, 0, 1).copy_(step.narrow(dim, 0, 1))
    smaller.narrow(dim, size - 1, 1).copy_(step.narrow(dim, size - 2, 1))
    # What stays undefined (NaN, inf) is 0.
    return smaller.nan_to_num_(nan=0.0, posinf=0.0)


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
        directions: (3, F, R, R) `texel_directions` of an identical map (same frames, field of
            view, resolution, dtype), to share rather than recompute; None computes them.

    Attributes:
        directions: (3, F, R, R) unit world direction of every texel-centre ray, by coordinate
            (12 bytes a texel in float32: computed once rather than at every lookup, which it
            made 2x slower).
    """

    def __init__(
        self,
        centre: torch.Tensor,
        face_from_world: torch.Tensor,
        tan_half_fov: float,
        resolution: int,
        directions: torch.Tensor | None = None,
    ):
        self.centre = centre
        self.face_from_world = face_from_world
        self.num_faces = face_from_world.shape[0]
        self.tan_half_fov = tan_half_fov
        self.resolution = resolution
        self.directions = self.texel_directions() if directions is None else directions

    def texel_directions(self) -> torch.Tensor:
        """(3, F, R, R) unit world direction of every texel-centre ray (see `directions`)."""
        index = torch.arange(self.resolution, device=self.centre.device)
        row, col = torch.meshgrid(index, index, indexing="ij")
        uv = self.texel_centre_uv(row, col) * self.tan_half_fov
        frame = self.face_from_world[:, None, None]
        return (
            torch.nn.functional.normalize(
                uv[..., 0:1] * frame[..., 0, :] + uv[..., 1:2] * frame[..., 1, :] + frame[..., 2, :], dim=-1
            )
            .permute(3, 0, 1, 2)
            .contiguous()
        )

    def affine_rays(self):
        """Origins: the centre; unnormalised directions: forward + u tan right + v tan up (see `RasterTarget`)."""
        frame = self.face_from_world
        origins = torch.zeros_like(frame)
        origins[:, 0] = self.centre
        return origins, torch.stack((frame[:, 2], self.tan_half_fov * frame[:, 0], self.tan_half_fov * frame[:, 1]), 1)

    def _offsets(self, x, y, z) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        cx, cy, cz = self.centre.tolist()
        return x - cx, y - cy, z - cz

    def project_components(self, x, y, z):
        """The only face's (a spot light's map) local coordinates, z forward."""
        offset = self._offsets(x, y, z)
        right, up, forward = (_combine(row, offset) for row in self.face_from_world[0].tolist())
        positive = forward > 0
        scale = torch.where(positive, forward, torch.ones_like(forward)) * self.tan_half_fov
        u, v = right / scale, up / scale
        inside = positive & (u.abs() <= 1.0) & (v.abs() <= 1.0)
        return torch.zeros_like(u, dtype=torch.long), u, v, _length(offset), inside

    def texel_rays(self, face, row, col):
        flat = (face * self.resolution + row) * self.resolution + col
        direction = torch.stack([_take(column, flat) for column in self.directions], dim=-1)
        return self.centre.expand_as(direction), direction

    def footprint(self, depth):
        return depth * (2.0 * self.tan_half_fov / self.resolution)

    def texel_plane(self, sample, normals, point_normal):
        cos = sum(_take(column, sample.flat) * normals[..., axis] for axis, column in enumerate(self.directions))
        return cos, point_normal - (normals * self.centre).sum(-1)

    def depth_of(self, x, y, z):
        return _length(self._offsets(x, y, z))

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

    def __init__(
        self,
        centre: torch.Tensor,
        resolution: int,
        directions: torch.Tensor | None = None,
        front: torch.Tensor | None = None,
    ):
        eye = torch.eye(3, device=centre.device, dtype=centre.dtype)
        faces = []
        for axis in range(3):
            for sign in (1.0, -1.0):
                forward = sign * eye[axis]
                right = eye[(axis + 1) % 3]
                faces.append(torch.stack((right, torch.linalg.cross(forward, right), forward)))
        super().__init__(centre, torch.stack(faces), 1.0, resolution, directions)
        self.window = None if front is None else self._front_window(front)

    def _front_window(self, front: torch.Tensor) -> torch.Tensor:
        """(F, 4) long texel box (col_start, row_start, num_cols, num_rows) of each face around its
        directions d with d . front >= 0, widened by FRONT_MARGIN_TEXELS; empty behind the light.

        A one-sided light (`front`: (3,) unit world normal of its emitting side, through the
        centre) lights no receiver behind its plane, and the segments of those it lights stay
        in front of it: the rest of the map is never read.
        """
        boxes = []
        for right, up, forward in self.face_from_world.tolist():
            # d(u, v) . front = a + b u + c v over the face's square of image coordinates.
            a, b, c = (sum(f * x for f, x in zip(front.tolist(), row, strict=True)) for row in (forward, right, up))
            corners = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
            values = [a + b * u + c * v for u, v in corners]
            kept = []  # the square clipped to a + b u + c v >= 0
            for k, (p, fp) in enumerate(zip(corners, values, strict=True)):
                q, fq = corners[(k + 1) % 4], values[(k + 1) % 4]
                if fp >= 0.0:
                    kept.append(p)
                if (fp >= 0.0) != (fq >= 0.0):
                    t = fp / (fp - fq)
                    kept.append((p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])))
            if not kept:
                boxes.append(torch.zeros(4, dtype=torch.long, device=self.centre.device))
                continue
            low = self.centre.new_tensor([min(u for u, _ in kept), min(v for _, v in kept)])
            high = self.centre.new_tensor([max(u for u, _ in kept), max(v for _, v in kept)])
            box = _bounds_from_uv(low, high, self.resolution)
            start = (box[:2] - FRONT_MARGIN_TEXELS).clamp_min(0)
            stop = (box[:2] + box[2:] + FRONT_MARGIN_TEXELS).clamp_max(self.resolution)
            boxes.append(torch.cat((start, stop - start)))
        return torch.stack(boxes)

    def texel_bounds(self, corners):
        """`PinholeMaps.texel_bounds` within each face's front window (when the light is one-sided)."""
        bounds = super().texel_bounds(corners)
        if self.window is None:
            return bounds
        window = self.window.unsqueeze(1)
        start = torch.maximum(bounds[..., :2], window[..., :2])
        stop = torch.minimum(bounds[..., :2] + bounds[..., 2:], window[..., :2] + window[..., 2:])
        return torch.cat((start, (stop - start).clamp_min(0)), dim=-1)

    def project_components(self, x, y, z):
        """The face of the offset o's dominant axis a, elementwise (an argmax over the faces' z was
        10x slower): face 2 a + [o_a < 0] has the frame (e_{a+1}, s e_{a+2}, s e_a), s the sign of
        o_a, so u = o_{a+1} / |o_a| and v = o_{a+2} / o_a (a (3, 3) product per face was 3x slower)."""
        ox, oy, oz = self._offsets(x, y, z)
        ax, ay, az = ox.abs(), oy.abs(), oz.abs()
        is_x = (ax >= ay) & (ax >= az)
        dtype = ox.dtype
        on_x, on_y = is_x.to(dtype), (~is_x & (ay >= az)).to(dtype)
        on_z = 1.0 - on_x - on_y
        major = ox * on_x + oy * on_y + oz * on_z
        size = major.abs().clamp_min(torch.finfo(dtype).tiny)
        u = (oy * on_x + oz * on_y + ox * on_z) / size
        v = (oz * on_x + ox * on_y + oy * on_z) * major.sign() / size
        face = (on_y + 2.0 * on_z) * 2.0 + (major < 0).to(dtype)
        # Every direction lies on a face (the centre itself reads the middle of face 0).
        return face, u, v, _length((ox, oy, oz)), None


def _combine(weights: list[float], components: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """sum_i weights[i] components[i] (a row of a frame applied to points given by their coordinates)."""
    return components[0] * weights[0] + components[1] * weights[1] + components[2] * weights[2]


def _length(components: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """Euclidean length of vectors given by their coordinates."""
    x, y, z = components
    return torch.sqrt(x * x + y * y + z * z)


class OrthoMap(DepthMap):
    """Parallel rays along `forward` through a square window of a plane above the occluders.

    Args:
        face_from_world: (3, 3) orthonormal rows (right, up, forward).
        window_centre: (3,) world centre of the window, on the starting plane.
        half_size: half the window's side (world units).
        resolution: texels per side.
    """

    def __init__(self, face_from_world: torch.Tensor, window_centre: torch.Tensor, half_size: float, resolution: int):
        self.face_from_world = face_from_world.unsqueeze(0)
        self.window_centre = window_centre
        self.half_size = half_size
        self.num_faces = 1
        self.resolution = resolution

    def _local(self, x, y, z, rows: slice) -> list[torch.Tensor]:
        cx, cy, cz = self.window_centre.tolist()
        offset = (x - cx, y - cy, z - cz)
        return [_combine(row, offset) for row in self.face_from_world[0, rows].tolist()]

    def project_components(self, x, y, z):
        right, up, depth = self._local(x, y, z, slice(None))
        u, v = right / self.half_size, up / self.half_size
        return torch.zeros_like(u, dtype=torch.long), u, v, depth, (u.abs() <= 1.0) & (v.abs() <= 1.0)

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

    def texel_plane(self, sample, normals, point_normal):
        right, up, forward = ((normals * row).sum(-1) for row in self.face_from_world[0])
        u, v = ((t.to(normals.dtype) + 0.5) * (2.0 / self.resolution) - 1.0 for t in (sample.col, sample.row))
        origin = (normals * self.window_centre).sum(-1) + (u * right + v * up) * self.half_size
        return forward.expand_as(origin), point_normal - origin

    def depth_of(self, x, y, z):
        return self._local(x, y, z, slice(2, 3))[0]

    def texel_bounds(self, corners):
        uv = ((corners - self.window_centre) @ self.face_from_world[0, :2].T) / self.half_size
        return _bounds_from_uv(uv.amin(dim=-2), uv.amax(dim=-2), self.resolution).unsqueeze(0)
