"""Subdivision surfaces at the bake camera: level, triangles, time and silhouette error.

    python -m pipeline.benchmarks.subdivision [--width W --height H] [--repeats N] [SHOT ...]

The sphere: a Catmull-Clark cube cage [-1, 1]^3 three units in front of a 50 mm / 36 mm camera.
It is read (`read_scene`: cage, level choice, refinement, limit surface, placement) N times; the
line gives the level and triangles chosen, the median wall and CPU seconds, and the silhouette
error: the largest distance in pixels between the outline of the refined triangles and that of
the limit surface (approximated two levels finer with its vertices on the limit; the shape is
convex, so both outlines are convex hulls of projected points). Each SHOT (e.g. the USD WG
teapot) is loaded with `load_scene` N times at the same size: median seconds, triangles and the
subdivision warnings. On a shared machine the wall time is an upper bound.
"""

from __future__ import annotations

import argparse

import numpy as np
from pxr import Gf, Usd, UsdGeom

from pipeline.benchmarks.stopwatch import Stopwatch
from pipeline.scene import load_scene
from pipeline.scene.camera import project
from pipeline.scene.load import read_scene
from pipeline.scene.subdivide import make_cage, refined_triangles
from pipeline.scene.types import Camera

CUBE_POINTS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
CUBE_FACES = np.array([[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]])
"""The cube [-1, 1]^3: point k = (x, y, z) with k = 4 x' + 2 y' + z' over {0, 1}; faces outward."""


def cube_cage_stage(
    scheme: str = "catmullClark", left_handed: bool = False, camera_distance: float = 3.0
) -> tuple[Usd.Stage, UsdGeom.Mesh]:
    """An in-memory stage: the cube cage as a subdivision mesh `/Cube` and a camera `/Cam` on +Z
    looking at it (50 mm focal length, 36 x 27 mm aperture)."""
    stage = Usd.Stage.CreateInMemory()
    mesh = UsdGeom.Mesh.Define(stage, "/Cube")
    faces = CUBE_FACES[:, ::-1] if left_handed else CUBE_FACES
    mesh.CreatePointsAttr([Gf.Vec3f(*p) for p in CUBE_POINTS])
    mesh.CreateFaceVertexCountsAttr([4] * len(faces))
    mesh.CreateFaceVertexIndicesAttr(faces.ravel().tolist())
    mesh.CreateSubdivisionSchemeAttr(scheme)
    if left_handed:
        mesh.CreateOrientationAttr(UsdGeom.Tokens.leftHanded)
    camera = UsdGeom.Camera.Define(stage, "/Cam")
    camera.AddTranslateOp().Set(Gf.Vec3d(0, 0, camera_distance))
    camera.CreateFocalLengthAttr(50.0)
    camera.CreateHorizontalApertureAttr(36.0)
    camera.CreateVerticalApertureAttr(27.0)
    return stage, mesh


def _outline(camera: Camera, positions: np.ndarray) -> np.ndarray:
    """(K, 2) pixel coordinates of the convex outline of the projected points, in order."""
    from scipy.spatial import ConvexHull

    pixels, _ = project(camera, positions.reshape(-1, 3).astype(np.float64))
    return pixels[ConvexHull(pixels).vertices]


def _distance_to_polygon(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """(P,) distance of each point to the boundary of a closed polygon (K, 2)."""
    start, edge = polygon, np.roll(polygon, -1, axis=0) - polygon
    t = np.clip(np.einsum("pec,ec->pe", points[:, None] - start[None], edge) / np.sum(edge * edge, -1), 0, 1)
    return np.linalg.norm(points[:, None] - (start[None] + t[..., None] * edge[None]), axis=-1).min(axis=1)


def silhouette_error(camera: Camera, positions: np.ndarray, limit_positions: np.ndarray) -> float:
    """Symmetric largest distance in pixels between the outlines of two convex point sets."""
    ours, limit = _outline(camera, positions), _outline(camera, limit_positions)
    return float(max(_distance_to_polygon(ours, limit).max(), _distance_to_polygon(limit, ours).max()))


def sphere_row(width: int, height: int, repeats: int) -> str:
    """One line for the cube-cage sphere (see the module docstring)."""
    stopwatch = Stopwatch()
    for _ in range(repeats):
        stage, _ = cube_cage_stage()
        with stopwatch.section():
            scene = read_scene(stage, "sphere", width=width, height=height)
    geometry, camera = scene.geometry, scene.cameras["/Cam"]
    level = round(np.log(geometry.num_triangles / 12) / np.log(4))
    limit = refined_triangles(make_cage(CUBE_POINTS, [4] * 6, CUBE_FACES.ravel()), "catmullClark", level + 2)
    error = silhouette_error(camera, geometry.positions, limit["positions"])
    wall, cpu = stopwatch.median_ms()
    return (
        f"sphere (cube cage) {width}x{height}: level {level}, {geometry.num_triangles:,} triangles, "
        f"read {wall / 1e3:.2f} s wall / {cpu / 1e3:.2f} s CPU (median of {repeats}), "
        f"silhouette within {error:.3f} px of the limit"
    )


def shot_row(shot: str, width: int, height: int, repeats: int) -> str:
    stopwatch = Stopwatch()
    for _ in range(repeats):
        with stopwatch.section():
            scene = load_scene(shot, width=width, height=height)
    wall, cpu = stopwatch.median_ms()
    notes = [w for w in scene.warnings if "subdivision" in w]
    return (
        f"{shot} {width}x{height}: {scene.geometry.num_triangles:,} triangles, load {wall / 1e3:.2f} s wall / "
        f"{cpu / 1e3:.2f} s CPU (median of {repeats}){'; ' + '; '.join(notes) if notes else ''}"
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("shots", nargs="*", metavar="SHOT")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    print(sphere_row(args.width, args.height, args.repeats), flush=True)
    for shot in args.shots:
        print(shot_row(shot, args.width, args.height, args.repeats), flush=True)


if __name__ == "__main__":
    main()
