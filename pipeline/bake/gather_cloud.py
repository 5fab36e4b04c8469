"""The gather cloud: samples over all surfaces by area, flattened into a square texture.

Creation follows the chapter's divide-and-conquer (Listing 9-1): a budget of samples and a set of
triangles are split together, the budget in proportion to the areas, until a group has one
sample (placed on an area-weighted random triangle of the group, standing for the group's whole
area) or one triangle (its budget of samples, each standing for an equal share). Two decisions:

* Triangles larger than the mean area per sample are first halved along their longest edge, so
  a big wall's samples are stratified over it like the rest instead of drawn at random.
* `split` is a plane through the group's centroids, across the longest axis of their bounding box,
  placed where the cumulative area reaches half.

The recursion runs level by level over all groups at once (sorting by group, then key), so no
Python loop visits triangles. Flattening (Listing 9-2) splits recursively into equal halves
across the principal axis of the features (20 p / diagonal, n), whose squared distances are the
chapter's `400 |dp|^2 + diagonal^2 |dn|^2` divided by diagonal^2; split k sets bit k (from the
top) of the sample's Morton index, even splits choosing the row half, odd splits the column half.

Gathers re-emit diffusely (Lambertian), with the albedo the whole UsdPreviewSurface BRDF reflects
under uniform incident light (`reemitted_albedo`, the bihemispherical reflectance), not the diffuse
colour alone: a metal's gathers would otherwise re-emit nothing. On the glossy scene under a dome
(80 x 60, 4,096 gathers, every coefficient kept, 8 bounces) the specular light that left metals and
plastics towards other surfaces was 31 % of the path tracer's indirect light. The direction of that
light is lost (a mirror's reflection of a lamp spreads like a matte surface's); its energy is kept.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from pipeline.scene.surface import evaluate_materials
from pipeline.scene.types import Scene
from relight_torch.brdf import preview_surface
from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.indirect_samples import GatherSamples
from relight_torch.math.sampling import cosine_hemisphere, sobol

# Bounds on the level-by-level loops (each level at least halves something).
MAX_REFINE_LEVELS = 48
MAX_SPLIT_LEVELS = 96
AREA_BLOCK = 1 << 20
"""Triangles whose areas and centroids are computed in float64 at once (bounds the temporaries)."""
POSITION_WEIGHT = 20.0
"""sqrt(400) of the chapter's distance, applied to positions divided by the scene diagonal."""
ALBEDO_PAIRS = 1024
"""(wo, wi) direction pairs of `reemitted_albedo`'s estimate, the same Sobol pairs for every point."""
ALBEDO_CHUNK = 1024
"""Points whose albedo is estimated together (bounds the (points, pairs, 3) temporaries)."""


def reemitted_albedo(params: PreviewSurfaceParams, num_pairs: int = ALBEDO_PAIRS) -> torch.Tensor:
    """(N, 3) bihemispherical reflectance of N points' UsdPreviewSurface BRDFs (diffuse, specular, clearcoat).

    rho = 1/pi * integral over wo and wi of f(wo, wi) cos(theta_o) cos(theta_i): the fraction of
    uniform incident radiance the surface reflects, which a Lambertian re-emitter of that albedo
    returns. Estimated with wo cosine-distributed and wi drawn by the BRDF's own sampler
    (`preview_surface.sample`, weight f cos / pdf), on `num_pairs` Sobol points shared by all points,
    so that equal materials get equal albedos.

    Args:
        params: N points' parameters (float32, CPU).
        num_pairs: direction pairs per point.
    """
    u = sobol(num_pairs, 4, seed=0, dtype=params.roughness.dtype)
    wo_local, _ = cosine_hemisphere(u[:, :2])
    albedo = torch.zeros_like(params.diffuse_color)
    for start in range(0, albedo.shape[0], ALBEDO_CHUNK):
        chunk = params.index(slice(start, start + ALBEDO_CHUNK))
        num_points = chunk.roughness.shape[0]
        wo = wo_local.expand(num_points, -1, -1)
        chunk = chunk.with_sample_axis()
        wi_local, pdf = preview_surface.sample(chunk, wo, u[:, 2:].expand(num_points, -1, -1))
        f_cos = preview_surface.eval(chunk, wo, wi_local) * wi_local[..., 2:].clamp(min=0.0)
        weight = torch.where((pdf > 0).unsqueeze(-1), f_cos / pdf.clamp(min=1e-20).unsqueeze(-1), 0.0)
        albedo[start : start + ALBEDO_CHUNK] = weight.mean(dim=1)
    return albedo


def triangle_areas(corners: np.ndarray) -> np.ndarray:
    """(T,) float64 areas of (T, 3, 3) triangles, in float64 a block at a time."""
    areas = np.empty(corners.shape[0])
    for first in range(0, corners.shape[0], AREA_BLOCK):
        block = corners[first : first + AREA_BLOCK].astype(np.float64)
        areas[first : first + AREA_BLOCK] = 0.5 * np.linalg.norm(
            np.cross(block[:, 1] - block[:, 0], block[:, 2] - block[:, 0]), axis=-1
        )
    return areas


def triangle_centroids(corners: np.ndarray, index: np.ndarray) -> np.ndarray:
    """(K, 3) float64 centroids of the triangles `index` (K,) of (T, 3, 3) `corners`, a block at a time."""
    centroids = np.empty((index.shape[0], 3))
    for first in range(0, index.shape[0], AREA_BLOCK):
        chosen = index[first : first + AREA_BLOCK]
        centroids[first : first + AREA_BLOCK] = corners[chosen].astype(np.float64).mean(axis=1)
    return centroids


def refine_triangles(
    corners: np.ndarray, uvs: np.ndarray, max_area: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Halve triangles along their longest edge until none is larger than `max_area`.

    Args:
        corners: (T, 3, 3) float positions; uvs: (T, 3, 2) per-corner uvs (split alongside).
        max_area: largest area to keep.

    Returns:
        (corners (T', 3, 3), uvs (T', 3, 2), parent (T',) int64 index of the input triangle); the
        winding of every piece is its parent's.
    """
    parent = np.arange(corners.shape[0])
    for _ in range(MAX_REFINE_LEVELS):
        big = triangle_areas(corners) > max_area
        if not big.any():
            break
        c, u = corners[big], uvs[big]
        edge_lengths = np.linalg.norm(np.roll(c, -1, axis=1) - c, axis=-1)
        roll = (np.argmax(edge_lengths, axis=1)[:, None] + np.arange(3)) % 3
        c = np.take_along_axis(c, roll[:, :, None], axis=1)
        u = np.take_along_axis(u, roll[:, :, None], axis=1)
        mid_c, mid_u = 0.5 * (c[:, 0] + c[:, 1]), 0.5 * (u[:, 0] + u[:, 1])
        corners = np.concatenate(
            [corners[~big], np.stack([c[:, 0], mid_c, c[:, 2]], 1), np.stack([mid_c, c[:, 1], c[:, 2]], 1)]
        )
        uvs = np.concatenate(
            [uvs[~big], np.stack([u[:, 0], mid_u, u[:, 2]], 1), np.stack([mid_u, u[:, 1], u[:, 2]], 1)]
        )
        parent = np.concatenate([parent[~big], parent[big], parent[big]])
    return corners, uvs, parent


def split_budget(
    centroids: np.ndarray, areas: np.ndarray, num_samples: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Listing 9-1's recursion: which triangle each sample lands on, and the area it stands for.

    Args:
        centroids: (T, 3) triangle centroids; areas: (T,) positive areas.
        num_samples: the budget (>= 1).
        rng: picks the triangle of one-sample groups.

    Returns:
        (triangle (num_samples,) int64, area (num_samples,) float64); areas sum to the total.

    Per triangle the recursion holds its order and group (int32) and one coordinate at a time:
    a production set's tens of millions of triangles are gigabytes per (T, 3) float64 copy. The
    inputs stay float64: the split's order and halves, and so every transfer cache's gathers, are
    those of float64 sums.
    """
    index_type = np.int32 if areas.shape[0] < 2**31 else np.int64
    order = np.arange(areas.shape[0], dtype=index_type)
    start, count = np.array([0]), np.array([areas.shape[0]])
    budget, group_area = np.array([num_samples]), np.array([areas.sum(dtype=np.float64)])
    for _ in range(MAX_SPLIT_LEVELS):
        active = (budget > 1) & (count > 1)
        if not active.any():
            break
        group = np.repeat(np.arange(start.shape[0], dtype=index_type), count)
        extent = np.stack(
            [
                np.maximum.reduceat(column, start) - np.minimum.reduceat(column, start)
                for column in (centroids[order, axis] for axis in range(3))
            ],
            axis=1,
        )
        key = centroids[order, np.argmax(extent, axis=1).astype(np.int8)[group]]
        order = order[np.lexsort((key, group))]
        del key
        ordered_areas = areas[order]
        cumulative = np.cumsum(ordered_areas, dtype=np.float64)
        before_group = cumulative[start] - ordered_areas[start]
        del ordered_areas
        within = cumulative - before_group[group]
        num_before_half = np.add.reduceat(within < 0.5 * group_area[group], start)
        left = np.clip(num_before_half + 1, 1, np.maximum(count - 1, 1))
        left_area = within[start + left - 1]
        del within, group, cumulative
        left_budget = np.clip((budget * left_area / group_area).astype(np.int64), 1, np.maximum(budget - 1, 1))
        # Each active group becomes (left, right); inactive groups stay as they are.
        start, count, budget, group_area = (
            _interleave(active, start, start, start + left),
            _interleave(active, count, left, count - left),
            _interleave(active, budget, left_budget, budget - left_budget),
            _interleave(active, group_area, left_area, group_area - left_area),
        )
    cumulative = np.cumsum(areas[order], dtype=np.float64)
    before_group = cumulative[start] - areas[order[start]]
    # One-sample groups: an area-weighted random triangle; one-triangle groups: all their samples on it.
    target = before_group + rng.random(start.shape[0]) * group_area
    pick = np.clip(np.searchsorted(cumulative, target, side="right"), start, start + count - 1)
    sample_group = np.repeat(np.arange(start.shape[0]), budget)
    triangle = order[pick][sample_group].astype(np.int64)
    return triangle, (group_area / budget)[sample_group]


def _interleave(active: np.ndarray, whole: np.ndarray, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """New per-group array: `whole` for inactive groups, `left` then `right` for active ones."""
    repeat = np.where(active, 2, 1)
    first = np.cumsum(repeat) - repeat
    out = np.empty(int(repeat.sum()), dtype=np.result_type(whole, left, right))
    out[first] = np.where(active, left, whole)
    out[first[active] + 1] = right[active]
    return out


def flatten_order(position: np.ndarray, normal: np.ndarray, diagonal: float) -> np.ndarray:
    """Listing 9-2: the texture position of each sample, similar samples in the same Haar blocks.

    Args:
        position, normal: (G, 3) with G = 4^L.
        diagonal: the scene's bounding-box diagonal.

    Returns:
        (G,) int64 permutation: texture cell t (row-major in the n x n square) holds sample
        `order[t]`.
    """
    num = position.shape[0]
    side = math.isqrt(num)
    num_levels = 2 * round(math.log2(side)) if side > 1 else 0
    features = np.concatenate([POSITION_WEIGHT * position / diagonal, normal], axis=1).astype(np.float64)
    morton = np.arange(num)
    for level in range(num_levels):
        groups = morton.reshape(1 << level, -1)
        f = features[groups]
        centred = f - f.mean(axis=1, keepdims=True)
        _, vectors = np.linalg.eigh(np.einsum("gmi,gmj->gij", centred, centred))
        projection = np.einsum("gmi,gi->gm", centred, vectors[..., -1])
        morton = np.take_along_axis(groups, np.argsort(projection, axis=1, kind="stable"), axis=1).reshape(-1)
    index = np.arange(num)
    row, col = np.zeros(num, np.int64), np.zeros(num, np.int64)
    for level in range(num_levels):
        bit = (index >> (num_levels - 1 - level)) & 1
        if level % 2 == 0:
            row = (row << 1) | bit
        else:
            col = (col << 1) | bit
    order = np.empty(num, np.int64)
    order[row * side + col] = morton
    return order


def create_gathers(scene: Scene, num_gathers: int, seed: int = 0) -> GatherSamples:
    """The scene's gather cloud, in texture order (CPU float32 tensors; object ids int64).

    Args:
        scene: the shot (its triangle soup and materials).
        num_gathers: a power of 4.
        seed: seed of the random placement.

    Raises:
        ValueError: num_gathers is not a power of 4, or the scene has no surface area.
    """
    side = math.isqrt(num_gathers)
    if num_gathers < 1 or side * side != num_gathers or side & (side - 1):
        raise ValueError(f"the number of gathers must be a power of 4, got {num_gathers}")
    geometry = scene.geometry
    areas = triangle_areas(geometry.positions)
    if not (areas > 0).any():
        raise ValueError("the scene has no surface area to place gathers on")
    max_area = areas.sum() / num_gathers
    # Only triangles larger than a gather's share are refined: the others (all but a few of a
    # production set's millions) are read where they lie, never copied whole.
    big = areas > max_area
    whole = np.flatnonzero((areas > 0) & ~big)
    pieces, piece_uvs, piece_parent = refine_triangles(
        geometry.positions[big].astype(np.float64), geometry.uvs[big], max_area
    )
    piece_source = np.flatnonzero(big)[piece_parent]
    del big
    rng = np.random.default_rng(seed)
    split_areas = np.concatenate([areas[whole], triangle_areas(pieces)])
    del areas  # 8 bytes a triangle, not needed by the split
    triangle, sample_area = split_budget(
        np.concatenate([triangle_centroids(geometry.positions, whole), pieces.mean(axis=1)]),
        split_areas,
        num_gathers,
        rng,
    )
    # Uniform point in each chosen triangle.
    u = rng.random((num_gathers, 2))
    root = np.sqrt(u[:, 0])
    weights = np.stack([1.0 - root, u[:, 1] * root, root * (1.0 - u[:, 1])], axis=1)
    is_piece = triangle >= whole.shape[0]
    source = np.empty_like(triangle)  # each gather's triangle in the soup
    source[~is_piece] = whole[triangle[~is_piece]]
    source[is_piece] = piece_source[triangle[is_piece] - whole.shape[0]]
    c = geometry.positions[source].astype(np.float64)
    c[is_piece] = pieces[triangle[is_piece] - whole.shape[0]]
    uvs = geometry.uvs[source].astype(np.float64)
    uvs[is_piece] = piece_uvs[triangle[is_piece] - whole.shape[0]]
    position = np.einsum("gc,gck->gk", weights, c)
    uv = np.einsum("gc,gck->gk", weights, uvs)
    normal = np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    material_id = geometry.material_ids[source]
    values = evaluate_materials(scene.materials, material_id, uv.astype(np.float32))
    values.pop("normal_tangent")
    params = PreviewSurfaceParams.from_numpy(values)
    points = geometry.positions.reshape(-1, 3)
    diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    order = flatten_order(position, normal, diagonal)
    columns = {
        "position": position,
        "normal": normal,
        "albedo": reemitted_albedo(params).numpy(),
        "emission": values["emissive_color"],
        "area": sample_area,
    }
    object_id = torch.from_numpy(geometry.object_ids[source][order].astype(np.int64))
    return GatherSamples(
        **{
            name: torch.from_numpy(np.ascontiguousarray(np.asarray(a)[order], np.float32))
            for name, a in columns.items()
        },
        object_id=object_id,
    )
