"""Where rays from uncovered samples meet (Kim et al. 2009, section III.1.B): secondary camera centres.

A grid of cubic cells of side delta = max box extent / n covers the workspace box. From each
uncovered sample, `num_rays` directions on its front hemisphere are traced up to the first surface
(Embree) or the box; every cell a ray passes through gains alpha w_i, the sample's importance. The
ray is walked in steps of half a cell, each cell counted once per ray, starting `min_distance`
(a fraction of the box's largest side) out: rays are densest next to their samples, so without it
the cells hugging a large uncovered patch win, and a camera there sees a sliver of it at grazing
angles.
The winner is the centre of the cell with the most votes.
"""

from __future__ import annotations

import numpy as np

from pipeline.bake.multiview.samples import SurfaceSamples
from pipeline.tracing import Tracer

MIN_DISTANCE = 0.1
"""Rays vote from this fraction of the box's largest side away from their sample."""


def hemisphere_directions(normals: np.ndarray, num_rays: int, rng: np.random.Generator) -> np.ndarray:
    """(M, R, 3) float32 directions uniform on the hemispheres around unit `normals` (M, 3)."""
    d = rng.normal(size=(normals.shape[0], num_rays, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    side = np.einsum("mrk,mk->mr", d, normals)
    return np.where(side[..., None] < 0, -d, d).astype(np.float32)


def _box_exit(origins: np.ndarray, directions: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(N,) ray parameter where rays from points inside the box leave it."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t_lo = (lo - origins) / directions
        t_hi = (hi - origins) / directions
    far = np.where(directions > 0, t_hi, np.where(directions < 0, t_lo, np.inf))
    return np.maximum(far.min(axis=-1), 0.0)


def vote(
    tracer: Tracer,
    samples: SurfaceSamples,
    lo: np.ndarray,
    hi: np.ndarray,
    grid_size: int,
    num_rays: int,
    rng: np.random.Generator,
    alpha: float = 1.0,
) -> tuple[np.ndarray, float]:
    """The best secondary camera position for `samples` (the uncovered ones).

    Returns:
        (centre (3,) float64 of the winning cell, its vote total).
    """
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    cell = float(np.max(hi - lo)) / grid_size
    dims = np.maximum(np.ceil((hi - lo) / cell).astype(np.int64), 1)
    directions = hemisphere_directions(samples.normal, num_rays, rng).reshape(-1, 3)
    starts = np.repeat(samples.position, num_rays, axis=0)
    origins = tracer.offset_origins(starts, np.repeat(samples.normal, num_rays, axis=0), directions)
    weights = np.repeat(samples.weight * alpha, num_rays)
    length = np.minimum(
        tracer.intersect(origins, directions).distance,
        _box_exit(origins.astype(np.float64), directions.astype(np.float64), lo, hi),
    )
    votes = np.zeros(int(np.prod(dims)), np.float64)
    step = 0.5 * cell
    num_steps = int(np.ceil(np.linalg.norm(hi - lo) / step))
    previous = np.full(origins.shape[0], -1, np.int64)
    for j in range(int(MIN_DISTANCE * grid_size / 0.5), num_steps):
        t = (j + 0.5) * step
        live = np.flatnonzero(length > t)
        if not live.size:
            break
        points = origins[live] + t * directions[live]
        index = np.clip(np.floor((points - lo) / cell).astype(np.int64), 0, dims - 1)
        flat = (index[:, 0] * dims[1] + index[:, 1]) * dims[2] + index[:, 2]
        new = flat != previous[live]
        votes += np.bincount(flat[new], weights[live][new], votes.size)
        previous[live] = flat
    best = int(np.argmax(votes))
    index = np.array(np.unravel_index(best, tuple(dims)))
    return lo + (index + 0.5) * cell, float(votes[best])
