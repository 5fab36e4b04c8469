"""Closed-form unshadowed irradiance from a polygonal light (Lambert 1760).

Lambert's formula for a convex polygon seen from a receiver at the origin, restricted to the
receiver's upper hemisphere (normal n):

    G = integral over the polygon of max(cos theta, 0) d omega = 1/2 |sum_i theta_i (n . Gamma_i)|

over the edges (v_i, v_i+1) of the polygon clipped by the tangent plane n . x = 0, theta_i the
angle the edge subtends and Gamma_i the unit normal of the plane through the origin and the edge.
A convex polygon crosses the tangent plane at 0 or 2 points; clipping adds the closing edge along
the horizon from where the boundary leaves the hemisphere to where it comes back (its Gamma is
+-n). G is a projected solid angle in sr (pi for a polygon covering the hemisphere); an
untextured light of radiance L gives the irradiance E = L G.

Lights with this closed form: untextured RectLights (one-sided: nothing reaches the side
their local +Z faces); `lights.ratio` uses it for the ratio estimator.
"""

from __future__ import annotations

import torch

from relight_torch.lights.geometry import LightFrame, surface_area
from relight_torch.lights.light import Light, LightKind
from relight_torch.math.extremes import extremes_of_four

CHUNK_POINTS = 1 << 16
"""Receivers evaluated together by `rect_cosine_integral`."""


def has_rect_closed_form(light: Light) -> bool:
    """Whether `rect_cosine_integral` gives the light's unshadowed irradiance (per unit radiance)."""
    return light.kind is LightKind.RECT and light.texture is None and surface_area(light) > 0.0


def _edge_term(
    ax: torch.Tensor,
    ay: torch.Tensor,
    az: torch.Tensor,
    bx: torch.Tensor,
    by: torch.Tensor,
    bz: torch.Tensor,
    nx: torch.Tensor,
    ny: torch.Tensor,
    nz: torch.Tensor,
) -> torch.Tensor:
    """theta (n . Gamma) of the edges a -> b (components, broadcasting): 0 for a degenerate edge.

    Gamma = (a x b) / |a x b|, theta = atan2(|a x b|, a . b); in-place on fresh temporaries (this
    runs per receiver and edge at every light move).
    """
    cx = ay * bz
    cx.sub_(az * by)
    cy = az * bx
    cy.sub_(ax * bz)
    cz = ax * by
    cz.sub_(ay * bx)
    projection = cx * nx
    projection.addcmul_(cy, ny).addcmul_(cz, nz)
    length = cx.square_().addcmul_(cy, cy).addcmul_(cz, cz).sqrt_()
    cosine = ax * bx
    cosine.addcmul_(ay, by).addcmul_(az, bz)
    # A degenerate edge has a x b = 0: projection 0 over a clamped length gives 0.
    return torch.atan2(length, cosine).mul_(projection).div_(length.clamp_min_(1e-30))


def _clipped_sum(v: list[torch.Tensor], n: list[torch.Tensor], height: torch.Tensor) -> torch.Tensor:
    """sum theta_i n . Gamma_i (M,) over closed polygons (components (K + 1, M)) cut by their
    tangent plane; height (K, M) of the first K vertices above it."""
    above = height > 0
    # Edge k runs from vertex k to vertex k + 1; p is where it meets the tangent plane (if it does).
    u, w = [c[:-1] for c in v], [c[1:] for c in v]
    next_height, next_above = height.roll(-1, 0), above.roll(-1, 0)
    crossing = above != next_above
    t = torch.where(crossing, height / torch.where(crossing, height - next_height, 1.0), 0.0)
    p = [a + t * (b - a) for a, b in zip(u, w, strict=True)]
    start = [torch.where(above, a, q) for a, q in zip(u, p, strict=True)]
    end = [torch.where(next_above, b, q) for b, q in zip(w, p, strict=True)]
    edges = torch.where(above | next_above, _edge_term(*start, *end, *n), 0.0).sum(0)
    # The horizon edge: from the crossing where the boundary leaves to the one where it re-enters.
    leaving, entering = crossing & above, crossing & next_above
    exit_point = [torch.where(leaving, q, 0.0).sum(0) for q in p]
    entry_point = [torch.where(entering, q, 0.0).sum(0) for q in p]
    return edges + _edge_term(*exit_point, *entry_point, *n)


def rect_cosine_integral(light: Light, points: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """G (N,) of a RectLight's emitting rectangle at receivers (N, 3) with unit normals (N, 3).

    0 behind the light (local z >= 0: the rect emits towards local -Z only). Any invertible
    affine transform is honoured: its corners are mapped to world space.

    Worked in an orthonormal frame of the light's plane (x, y in the plane, z along its normal),
    where every corner has z = 0: for an edge c -> d seen from p, a = c - p and b = d - p
    share a_z = b_z = Z, so a x b = (-e_y Z, e_x Z, a_x b_y - a_y b_x) with e = d - c, and each
    edge costs a few multiply-adds of per-receiver rows (U_i, V_i) = corner_i - p. Receivers whose
    tangent plane cuts the light are summed over the clipped polygon (`_clipped_sum`). The
    receivers go to that frame in one product, as component rows; the edges are evaluated in
    blocks of CHUNK_POINTS receivers, whose temporaries stay in cache (2-3x faster on a CPU than
    one pass).
    """
    frame = LightFrame.of(light, points)
    half_x, half_y = 0.5 * light.width, 0.5 * light.height
    corners_local = torch.tensor(
        [
            [half_x, half_y, 0.0],
            [-half_x, half_y, 0.0],
            [-half_x, -half_y, 0.0],
            [half_x, -half_y, 0.0],
            [half_x, half_y, 0.0],
        ],
        device=points.device,
        dtype=points.dtype,
    )
    corners = frame.point_to_world(corners_local)  # (5, 3): closed
    origin = corners[0]
    along = torch.nn.functional.normalize(corners[1] - origin, dim=0)
    plane_normal = torch.nn.functional.normalize(torch.linalg.cross(corners[1] - origin, corners[3] - origin), dim=0)
    rotation = torch.stack((along, torch.linalg.cross(plane_normal, along), plane_normal))  # rows: x, y, z
    x, y = ((corners - origin) @ rotation[:2].T).T.tolist()  # corner coordinates (z = 0), closed
    # (3, N) rows; a (3, 3) by transposed (3, N) product is 8x faster on the CPU than the
    # contiguous copy of a product's transpose.
    position, normal = rotation @ (points - origin).T, rotation @ normals.T
    # The receiver's local z is (p - corner) . light_from_world[2], a row normal to the light's
    # plane: its sign is that of the receiver's z in the plane's frame (-Z) times that row's
    # component along the plane's normal.
    facing = float(frame.light_from_world[2] @ plane_normal)
    blocks = [
        _rect_block(
            x,
            y,
            -position[2, i : i + CHUNK_POINTS],
            position[0, i : i + CHUNK_POINTS],
            position[1, i : i + CHUNK_POINTS],
            normal[:, i : i + CHUNK_POINTS],
            facing,
        )
        for i in range(0, max(points.shape[0], 1), CHUNK_POINTS)
    ]  # one (empty) block for no receivers
    return blocks[0] if len(blocks) == 1 else torch.cat(blocks)


def _rect_block(
    x: list[float],
    y: list[float],
    z: torch.Tensor,
    px: torch.Tensor,
    py: torch.Tensor,
    normal: torch.Tensor,
    facing: float,
) -> torch.Tensor:
    """G (M,) of M receivers in the light plane's frame (`rect_cosine_integral`).

    Args:
        x, y: the closed corners' in-plane coordinates (5 each).
        z: (M,) Z = -(the receivers' distance along the plane's normal); px, py: (M,) their
            in-plane coordinates (the frame's origin: corner 0).
        normal: (3, M) their unit normals in the plane's frame.
        facing: the sign of the light's local z against the plane's normal (G is 0 where
            -Z facing >= 0: behind the light, or in its plane).
    """
    nx, ny, nz = normal
    z2 = z.square()
    u = [x[i] - px for i in range(4)]
    v = [y[i] - py for i in range(4)]
    height = [(nx * u[i]).addcmul_(ny, v[i]).addcmul_(nz, z) for i in range(4)]  # above the tangent plane
    highest, lowest = extremes_of_four(height)
    slope_x, slope_y = z * ny, z * nx  # the in-plane part of n . (a x b) is Z (n_y e_x - n_x e_y)
    total = torch.zeros_like(px)
    for i in range(4):
        j = (i + 1) % 4
        ex, ey = x[i + 1] - x[i], y[i + 1] - y[i]
        cross_z = u[i] * v[j]
        cross_z.addcmul_(v[i], u[j], value=-1.0)
        projection = (slope_x * ex).sub_(slope_y, alpha=ey).addcmul_(nz, cross_z)
        length = cross_z.square_().add_(z2, alpha=ex * ex + ey * ey).sqrt_()
        cosine = (u[i] * u[j]).addcmul_(v[i], v[j]).add_(z2)
        total.add_(torch.atan2(length, cosine).mul_(projection).div_(length.clamp_min_(1e-30)))
    total.masked_fill_(lowest <= 0, 0.0)  # wholly above the tangent plane, or clipped below
    cut = torch.nonzero((lowest <= 0) & (highest > 0)).squeeze(-1)
    if cut.numel():
        closed = [torch.stack([c[k].index_select(0, cut) for k in (0, 1, 2, 3, 0)]) for c in (u, v)]
        total.index_copy_(
            0,
            cut,
            _clipped_sum(
                [*closed, z.index_select(0, cut).expand(5, -1)],
                [c.index_select(0, cut) for c in (nx, ny, nz)],
                torch.stack([h.index_select(0, cut) for h in height]),
            ),
        )
    return total.abs_().mul_(0.5).masked_fill_(z * facing <= 0, 0.0)
