"""Maximal empty spheres of the workspace (Kim et al. 2009, section III.1.A): primary camera centres.

The surfaces are approximated by the surface samples, the workspace bounded by a box. A search
starts at p_s + delta n_s above a random sample and repeats: grow the sphere until it touches a
sample or the box (its radius is the distance to the nearest one, found with a k-d tree, rather
than grown delta by delta); take the contacts, the samples and box points within radius + delta;
move the centre by delta along a direction d with d . (r_i - c) <= 0 for every contact r_i
(eq. 1). When no such direction exists the sphere is maximal. d is the negated mean of the unit
directions to the contacts when that satisfies eq. 1, else the solution of the small linear
program max t s.t. d . (r_i - c) / |r_i - c| <= -t, |d|_inf <= 1 (t <= 0: maximal). Searches stop
after `patience` consecutive ones find nothing new: a search ends early, as no news, when its
sphere enters one already found (centre within half the larger radius), and a sphere under
half the largest radius found is no news either. The spheres come back largest first.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linprog
from scipy.spatial import cKDTree

from pipeline.bake.multiview.samples import SurfaceSamples

MIN_RADIUS_FRACTION = 0.5
"""A maximal sphere under this fraction of the largest found is no news (it would not be chosen)."""


@dataclass(frozen=True)
class Sphere:
    centre: np.ndarray
    radius: float


def _box_contacts(centre: np.ndarray, reach: float, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(B, 3) feet of the perpendiculars from `centre` to the box faces closer than `reach`."""
    feet = []
    for axis in range(3):
        for bound in (lo[axis], hi[axis]):
            if abs(centre[axis] - bound) <= reach:
                foot = centre.copy()
                foot[axis] = bound
                feet.append(foot)
    return np.array(feet).reshape(-1, 3)


def _escape_direction(units: np.ndarray) -> np.ndarray | None:
    """A unit d with d . u_i < 0 for every unit contact direction u_i (K, 3), or None (maximal)."""
    mean = -units.mean(axis=0)
    norm = np.linalg.norm(mean)
    if norm > 1e-9 and np.all(units @ (mean / norm) < -1e-3):
        return mean / norm
    # Variables (d_x, d_y, d_z, t): minimise -t subject to u_i . d + t <= 0.
    result = linprog(
        c=[0, 0, 0, -1],
        A_ub=np.hstack([units, np.ones((len(units), 1))]),
        b_ub=np.zeros(len(units)),
        bounds=[(-1, 1)] * 3 + [(0, 1)],
        method="highs",
    )
    if not result.success or result.x[3] <= 1e-6:
        return None
    return result.x[:3] / np.linalg.norm(result.x[:3])


def _known(centre: np.ndarray, radius: float, known: list[Sphere]) -> bool:
    """Whether a sphere at `centre` is one of `known` (its centre within half the larger radius)."""
    if not known:
        return False
    centres = np.array([s.centre for s in known])
    radii = np.array([s.radius for s in known])
    return bool(np.any(np.linalg.norm(centres - centre, axis=-1) < 0.5 * np.maximum(radii, radius)))


def grow_sphere(
    tree: cKDTree,
    points: np.ndarray,
    start: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    delta: float,
    max_steps: int,
    known: list[Sphere] = (),
) -> Sphere | None:
    """One search from `start`: grow, move off the contacts by delta, until maximal (or max_steps).

    Returns None as soon as the sphere enters one of `known` (it would converge to it).
    """
    centre = np.clip(np.asarray(start, np.float64), lo, hi)
    for _ in range(max_steps):
        nearest, _ = tree.query(centre)
        radius = float(min(nearest, np.min(centre - lo), np.min(hi - centre)))
        if _known(centre, radius, known):
            return None
        contacts = points[tree.query_ball_point(centre, radius + delta)]
        contacts = np.concatenate([contacts, _box_contacts(centre, radius + delta, lo, hi)])
        offsets = contacts - centre
        lengths = np.linalg.norm(offsets, axis=-1)
        units = offsets[lengths > 1e-12] / lengths[lengths > 1e-12, None]
        direction = _escape_direction(units) if len(units) else None
        if direction is None:
            return Sphere(centre, radius)
        centre = np.clip(centre + delta * direction, lo, hi)
    nearest, _ = tree.query(centre)
    return Sphere(centre, float(min(nearest, np.min(centre - lo), np.min(hi - centre))))


def maximal_spheres(
    samples: SurfaceSamples,
    lo: np.ndarray,
    hi: np.ndarray,
    delta: float,
    patience: int,
    rng: np.random.Generator,
    max_steps: int = 400,
    max_searches: int = 1000,
) -> list[Sphere]:
    """Maximal empty spheres, largest first (see the module docstring).

    Args:
        samples: the surface samples (the surfaces' stand-in).
        lo, hi: (3,) the workspace box.
        delta: seed offset and step (scene units).
        patience: k, consecutive searches finding nothing new before stopping.
        max_searches: a bound on the searches in all.
    """
    points = samples.position.astype(np.float64)
    tree = cKDTree(points)
    spheres: list[Sphere] = []
    misses = 0
    for _ in range(max_searches):
        if misses >= patience:
            break
        i = int(rng.integers(samples.num_samples))
        sphere = grow_sphere(tree, points, points[i] + delta * samples.normal[i], lo, hi, delta, max_steps, spheres)
        largest = max((s.radius for s in spheres), default=0.0)
        if (
            sphere is None
            or sphere.radius <= max(delta, MIN_RADIUS_FRACTION * largest)
            or _known(sphere.centre, sphere.radius, spheres)
        ):
            misses += 1
            continue
        spheres.append(sphere)
        misses = 0
    return sorted(spheres, key=lambda s: -s.radius)
