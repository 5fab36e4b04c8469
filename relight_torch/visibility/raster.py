"""Depth rasterisation of a triangle soup in torch: one exact ray per texel centre.

A depth map (see `relight_torch.visibility.depth_maps`) is F faces of R x R texels, each texel
the ray through its centre. `rasterise_depth` finds, for every texel, the nearest triangle along
that ray. It enumerates the texels inside each triangle's texel bounding box on each face (the
bounding boxes come from the map's projection, clipped to the face), flattens all (triangle,
texel) candidates into one index range, and processes that range in chunks: ray-triangle test
(Moeller-Trumbore, two-sided) and `scatter_reduce(..., 'amin')` into the map. The only Python
loop is over chunks.

Decision: an exact ray test per candidate texel rather than splatting area-proportional point
samples with scatter_reduce('amin') (the splatter was reasoned about, not built). Splatting
needs a footprint wide enough to close the holes between samples, which dilates occluders
(over-darkening at silhouettes) and quantises depth to the sample's texel; the per-texel ray
gives the exact depth at the texel centre, leaves no holes between triangles sharing an edge
(barycentric tests are inclusive by `BARYCENTRIC_SLACK`), and its exact depth is what lets the
lookup recognise the receiver's own plane without a world epsilon. Its cost is the sum of the
triangles' texel bounding boxes (large thin diagonal triangles waste candidates): on this
project's shared 2-core CPU, a 1024^2 cube map of the 30-triangle Cornell box (its walls fill
all six faces) builds in about 6 s, of the 11k-triangle glossy scene in about 4.6 s.
"""

from __future__ import annotations

from typing import Protocol

import torch

# (triangle, texel) candidates tested together: bounds the (M, 3, 3) gathered corners (~100 bytes each).
CHUNK_CANDIDATES = 1 << 21
# Slack on the barycentric inside test (dimensionless), so that a texel centre on an edge shared
# by two triangles is not lost to rounding in both.
BARYCENTRIC_SLACK = 1e-6


class RasterTarget(Protocol):
    """What `rasterise_depth` needs from a depth map."""

    num_faces: int
    resolution: int

    def texel_bounds(self, corners: torch.Tensor) -> torch.Tensor:
        """(F, T, 4) long (col_start, row_start, num_cols, num_rows) of each triangle's texels per face."""
        ...

    def texel_rays(self, face: torch.Tensor, row: torch.Tensor, col: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(origins (M, 3), unit directions (M, 3)) of the rays through texel centres."""
        ...


def ray_triangle_distance(origins: torch.Tensor, directions: torch.Tensor, corners: torch.Tensor) -> torch.Tensor:
    """Distance along rays to triangles, two-sided (Moeller-Trumbore).

    Args:
        origins: (M, 3) world ray origins.
        directions: (M, 3) unit world ray directions.
        corners: (M, 3, 3) world triangle corners, one triangle per ray.

    Returns:
        (M,) ray parameter t >= 0 of the hit, inf on a miss or for a ray in the triangle's plane.
    """
    edge1 = corners[:, 1] - corners[:, 0]
    edge2 = corners[:, 2] - corners[:, 0]
    p = torch.linalg.cross(directions, edge2)
    det = (edge1 * p).sum(-1)
    usable = det.abs() > torch.finfo(det.dtype).tiny
    inv_det = 1.0 / torch.where(usable, det, torch.ones_like(det))
    to_origin = origins - corners[:, 0]
    u = (to_origin * p).sum(-1) * inv_det
    q = torch.linalg.cross(to_origin, edge1)
    v = (directions * q).sum(-1) * inv_det
    t = (edge2 * q).sum(-1) * inv_det
    inside = usable & (u >= -BARYCENTRIC_SLACK) & (v >= -BARYCENTRIC_SLACK) & (u + v <= 1.0 + BARYCENTRIC_SLACK)
    return torch.where(inside & (t >= 0), t, torch.full_like(t, torch.inf))


def rasterise_depth(target: RasterTarget, corners: torch.Tensor) -> torch.Tensor:
    """Nearest-hit depth of every texel of a map.

    Args:
        target: the map's projection (faces, resolution, texel bounds and rays).
        corners: (T, 3, 3) world triangle corners (the map's device and dtype).

    Returns:
        (F, R, R) distance along each texel-centre ray to the nearest triangle, inf where none.
    """
    num_faces, resolution = target.num_faces, target.resolution
    depth = torch.full((num_faces * resolution * resolution,), torch.inf, device=corners.device, dtype=corners.dtype)
    bounds = target.texel_bounds(corners)
    counts = bounds[..., 2] * bounds[..., 3]
    face, triangle = torch.nonzero(counts > 0, as_tuple=True)
    if face.numel() == 0:
        return depth.reshape(num_faces, resolution, resolution)
    box = bounds[face, triangle]
    ends = torch.cumsum(counts[face, triangle], 0)
    starts = ends - counts[face, triangle]
    total = int(ends[-1])
    for first in range(0, total, CHUNK_CANDIDATES):
        candidate = torch.arange(first, min(first + CHUNK_CANDIDATES, total), device=corners.device)
        owner = torch.searchsorted(ends, candidate, right=True)
        offset = candidate - starts[owner]
        col = box[owner, 0] + offset % box[owner, 2]
        row = box[owner, 1] + offset // box[owner, 2]
        origins, directions = target.texel_rays(face[owner], row, col)
        t = ray_triangle_distance(origins, directions, corners[triangle[owner]])
        hit = torch.isfinite(t)
        texel = (face[owner] * resolution + row) * resolution + col
        depth.scatter_reduce_(0, texel[hit], t[hit], reduce="amin")
    return depth.reshape(num_faces, resolution, resolution)
