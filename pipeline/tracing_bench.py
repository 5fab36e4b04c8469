"""Throughput of `pipeline.tracing.Tracer` against raw embreex calls on the same rays.

The question it answers: how much of Embree's speed does our layer (chunking, validation,
attribute gathers, threads) keep? It times, on one scene and one batch of coherent camera rays:
    * closest hit: raw `EmbreeScene.run(..., output=1)` vs `Tracer.intersect`, alone (distance,
      ids, barycentrics) and followed by reading every lazily computed attribute of the `Hits`,
    * occlusion: raw `run(..., query='OCCLUDED')` vs `Tracer.occluded`, on shadow rays from the
      camera rays' hit points to a point light behind and above the scene,
with our layer on one thread (the like-for-like ratio) and on all the threads it would use.
The default scene is a synthetic displaced heightfield, so the benchmark needs no asset.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import numpy as np
from embreex import mesh_construction, rtcore_scene

from pipeline.scene.types import Geometry
from pipeline.tracing import Hits, Tracer

# The surface attributes `Hits` computes on first access.
HIT_ATTRIBUTES = ("position", "geometric_normal", "shading_normal", "uv", "material_id", "object_id")


@dataclass(frozen=True)
class Timing:
    """One row of the benchmark table.

    Attributes:
        query: 'closest hit' or 'occlusion'.
        implementation: 'raw embreex', 'Tracer, K threads' (traversal only: distance, ids,
            barycentrics) or 'Tracer + attributes, K threads' (and every surface attribute).
        num_rays: rays per call.
        median_seconds: median wall time of one call over the repeats.
        ratio: this row's rays/s over the raw embreex row's of the same query.
    """

    query: str
    implementation: str
    num_rays: int
    median_seconds: float
    ratio: float

    @property
    def rays_per_second(self) -> float:
        return self.num_rays / self.median_seconds


def heightfield_geometry(num_triangles: int) -> Geometry:
    """A displaced grid over [-1, 1]^2 (z up) with about `num_triangles` triangles.

    Heights are a sum of two sine waves (amplitudes 0.1 and 0.05), so neighbouring rays hit neighbouring
    triangles as in a real shot. Normals are the analytic surface normals at the corners, uvs the
    grid coordinates in [0, 1]^2, material ids the quadrant (0..3), object id 0.

    Args:
        num_triangles: target count; the grid has 2 n^2 triangles with
            n = max(1, round(sqrt(num_triangles / 2))).

    Returns:
        the Geometry.
    """
    num_cells = max(1, round(np.sqrt(num_triangles / 2)))
    coords = np.linspace(-1.0, 1.0, num_cells + 1)
    x, y = np.meshgrid(coords, coords, indexing="xy")
    height = 0.1 * np.sin(7 * x) * np.cos(5 * y) + 0.05 * np.sin(23 * x + 17 * y)
    # Normal of z = h(x, y): (-dh/dx, -dh/dy, 1), normalised.
    dh_dx = 0.7 * np.cos(7 * x) * np.cos(5 * y) + 1.15 * np.cos(23 * x + 17 * y)
    dh_dy = -0.5 * np.sin(7 * x) * np.sin(5 * y) + 0.85 * np.cos(23 * x + 17 * y)
    normal = np.stack([-dh_dx, -dh_dy, np.ones_like(x)], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    grid = {
        "positions": np.stack([x, y, height], axis=-1),
        "normals": normal,
        "uvs": np.stack([(x + 1) / 2, (y + 1) / 2], axis=-1),
    }
    # Each cell (a = lower-left, b = lower-right, c = upper-right, d = upper-left) is split into
    # the counter-clockwise triangles (a, b, c) and (a, c, d), whose normals point to +z.
    corner_soups = {}
    for name, values in grid.items():
        a, b = values[:-1, :-1], values[:-1, 1:]
        c, d = values[1:, 1:], values[1:, :-1]
        triangles = np.concatenate([np.stack([a, b, c], axis=-2), np.stack([a, c, d], axis=-2)])
        corner_soups[name] = triangles.reshape(-1, 3, values.shape[-1]).astype(np.float32)
    centroid = corner_soups["positions"].mean(axis=1)
    quadrant = (centroid[:, 0] > 0).astype(np.int32) + 2 * (centroid[:, 1] > 0).astype(np.int32)
    return Geometry(
        positions=corner_soups["positions"],
        normals=corner_soups["normals"],
        uvs=corner_soups["uvs"],
        material_ids=quadrant,
        object_ids=np.zeros(len(quadrant), np.int32),
    )


def pinhole_rays(
    eye: np.ndarray, target: np.ndarray, vertical_fov_degrees: float, width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    """Coherent camera rays through the pixel centres of a look-at pinhole (world up = +z).

    Args:
        eye: (3,) camera position.
        target: (3,) point the camera looks at.
        vertical_fov_degrees: full vertical field of view.
        width, height: image size in pixels; row 0 is the top.

    Returns:
        origins (H * W, 3) float32 and unit directions (H * W, 3) float32, row-major.
    """
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    half_height = np.tan(np.radians(vertical_fov_degrees) / 2)
    half_width = half_height * width / height
    screen_x = ((np.arange(width) + 0.5) / width * 2 - 1) * half_width
    screen_y = (1 - (np.arange(height) + 0.5) / height * 2) * half_height
    sx, sy = np.meshgrid(screen_x, screen_y, indexing="xy")
    directions = forward + sx[..., None] * right + sy[..., None] * up
    directions = (directions / np.linalg.norm(directions, axis=-1, keepdims=True)).reshape(-1, 3)
    origins = np.broadcast_to(eye, directions.shape)
    return origins.astype(np.float32), directions.astype(np.float32)


def synthetic_rays(num_rays: int) -> tuple[np.ndarray, np.ndarray]:
    """About `num_rays` square-image camera rays looking down at `heightfield_geometry` from
    above its near edge; about 70 % hit, the top rows see past the far edge and miss."""
    side = max(1, round(np.sqrt(num_rays)))
    return pinhole_rays(np.array([0.0, -1.8, 1.5]), np.array([0.0, 0.0, -0.1]), 45.0, side, side)


def shadow_rays(
    tracer: Tracer, origins: np.ndarray, directions: np.ndarray, light_position: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays from the camera rays' hit points (offset off the surface) to a point light.

    Returns:
        origins (M, 3) float32, unit directions (M, 3) float32 and t_far (M,) float32 (the
        distance to the light less `tracer.epsilon`), for the M camera rays that hit.
    """
    hits = tracer.intersect(origins, directions)
    points = hits.position[hits.hit]
    to_light = (light_position - points).astype(np.float32)
    distance = np.linalg.norm(to_light, axis=-1)
    shadow_directions = (to_light / distance[:, None]).astype(np.float32)
    shadow_origins = tracer.offset_origins(points, hits.geometric_normal[hits.hit], shadow_directions)
    return shadow_origins, shadow_directions, (distance - tracer.epsilon).astype(np.float32)


def light_position(geometry: Geometry) -> np.ndarray:
    """(3,) a point light behind and above the scene: centre + diagonal * (0, 1, 1).

    Seen from `synthetic_rays`' camera it lights the heightfield from the far side, so that
    about a fifth of the shadow rays are blocked (mostly by the waves facing away from it).
    """
    points = geometry.positions.reshape(-1, 3).astype(np.float64)
    lo, hi = points.min(axis=0), points.max(axis=0)
    return (lo + hi) / 2 + np.linalg.norm(hi - lo) * np.array([0.0, 1.0, 1.0])


def median_seconds(call: Callable[[], object], repeats: int) -> float:
    """Median wall time of `call()` over `repeats` runs, after one warm-up run."""
    call()
    seconds = []
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        seconds.append(time.perf_counter() - start)
    return float(np.median(seconds))


def run_benchmark(
    geometry: Geometry, origins: np.ndarray, directions: np.ndarray, repeats: int = 5, num_threads: int | None = None
) -> list[Timing]:
    """Time raw embreex against `Tracer` on the same scene and rays.

    Args:
        geometry: the scene.
        origins, directions: (N, 3) float32 camera rays.
        repeats: timed runs per row (the median is reported).
        num_threads: threads of the multi-threaded `Tracer` row (default: all usable CPUs).

    Returns:
        Rows for closest hit then occlusion: raw, then Tracer on 1 thread and on K threads.
    """
    raw_scene = rtcore_scene.EmbreeScene(robust=True)
    mesh_construction.TriangleMesh(raw_scene, geometry.positions)
    single = Tracer(geometry, num_threads=1)
    multi = Tracer(geometry, num_threads=num_threads)
    shadow_origins, shadow_directions, shadow_t_far = shadow_rays(single, origins, directions, light_position(geometry))
    # Raw calls get the same per-call inputs ours builds (a fresh t_far, which embreex overwrites).
    num_rays = len(origins)
    closest_hit = {
        "raw embreex": lambda: raw_scene.run(origins, directions, dists=np.full(num_rays, np.inf, np.float32), output=1)
    }
    occlusion = {
        "raw embreex": lambda: raw_scene.run(
            shadow_origins, shadow_directions, dists=shadow_t_far.copy(), query="OCCLUDED"
        )
    }
    for tracer in (single, multi):
        threads = f"{tracer.num_threads} thread{'s' if tracer.num_threads > 1 else ''}"
        closest_hit[f"Tracer, {threads}"] = partial(tracer.intersect, origins, directions)
        closest_hit[f"Tracer + attributes, {threads}"] = partial(
            _intersect_with_attributes, tracer, origins, directions
        )
        occlusion[f"Tracer, {threads}"] = partial(tracer.occluded, shadow_origins, shadow_directions, shadow_t_far)
    timings = []
    for query, num_query_rays, calls in (
        ("closest hit", num_rays, closest_hit),
        ("occlusion", len(shadow_origins), occlusion),
    ):
        seconds = {name: median_seconds(call, repeats) for name, call in calls.items()}
        timings += [
            Timing(query, name, num_query_rays, elapsed, seconds["raw embreex"] / elapsed)
            for name, elapsed in seconds.items()
        ]
    return timings


def _intersect_with_attributes(tracer: Tracer, origins: np.ndarray, directions: np.ndarray) -> Hits:
    """`tracer.intersect`, then every lazily computed surface attribute of the hits."""
    hits = tracer.intersect(origins, directions)
    for name in HIT_ATTRIBUTES:
        getattr(hits, name)
    return hits


def format_table(timings: list[Timing]) -> str:
    """The timings as an aligned text table, one row per (query, implementation)."""
    header = f"{'query':<12} {'implementation':<30} {'rays':>9} {'median ms':>10} {'Mrays/s':>8} {'ours/raw':>8}"
    lines = [header, "-" * len(header)]
    for timing in timings:
        lines.append(
            f"{timing.query:<12} {timing.implementation:<30} {timing.num_rays:>9} "
            f"{timing.median_seconds * 1e3:>10.1f} {timing.rays_per_second / 1e6:>8.2f} "
            f"{timing.ratio:>8.2f}"
        )
    return "\n".join(lines)
