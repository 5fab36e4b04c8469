"""Moving-camera relighting along a camera path, against the reference, per coverage threshold.

    python -m pipeline.benchmarks.multiview_path SCENE [SCENE...] [--width 640 --height 480]
        [--views 8] [--coverage 0.1 0.05 0.02] [--caching-resolution 512] [--spp 16]
        [--sample-groups G] [--blend-lighting] [--edge-contrast C|none] [--near-field F|none] [--threads T]
        [--fill-holes] [--no-reference] [--reuse-bake] [--out DIR] [--csv FILE] [--table FILE]

Per scene and coverage threshold it bakes a multiview cache (placement and one deep framebuffer
per caching camera), then renders a path of `--views` novel views: the shot camera orbited about
the point its centre pixel sees, by yaw angles spread over +-`--yaw` degrees and a rise of up to
5 % of the scene's extent. Per view: PSNR against `PathTracer(max_bounces=0)` over all pixels and
over the covered ones (pixels whose every sub-sample found a cache sample, or was baked on
demand), the PSNR of a direct cache baked for that very view (the ceiling: what the view's own
deep framebuffer, same supersampling, two texture samples, reaches), the hole fraction before
and after the small holes are filled, and median times of
the three steps of a camera move: primary rays (Embree, CPU), the correspondence map
(`MultiviewRelighter.set_view`: eq. 5, hole filling, GBuffer gather, a Relighter over the view)
and the re-render (`render` with every light's images dropped: the cached lighting of the
caching samples gathered and the BRDF evaluated at the view; the shadow rays it traced are
counted per re-render, `rerender_rays`: once `prepare_lighting` has lit the pool, only those of
the points on a light's edges, `--edge-contrast`, or in its near field, `--near-field`), and of a
light move
re-rendered at that view (`relight_ms`, the shared measure: the moved light's lighting is traced
again for the caching samples the view uses). Timings are warm medians of `--repeats` runs,
wall time (an upper bound on a shared machine) and, for the three steps, this process's CPU time
(all its threads); `--threads` sets torch's and Embree's threads.

Output: the shared sweep CSV (one row per scene and threshold, light edit 'shot': psnr_db and
rel_mse averaged over the path, cache_bytes, bake_s, relight_ms the median light move over the
views; params name the threshold, the cameras chosen and the path) and a per-view CSV table.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import io
import sys
import time
from pathlib import Path

import numpy as np
import torch

from pipeline.bake.adapter import cache_bytes, format_params
from pipeline.bake.deep_framebuffer import bake_deep_framebuffer
from pipeline.bake.multiview.bake import bake_multiview
from pipeline.bake.multiview.frames import FrameRenderer
from pipeline.bake.multiview.placement import PlacementSettings
from pipeline.bake.multiview.view import view_points
from pipeline.benchmarks.bench.measure import relight_ms
from pipeline.benchmarks.reuse import reusable_bake
from pipeline.benchmarks.rows import SweepRow, write_csv
from pipeline.benchmarks.stopwatch import Stopwatch
from pipeline.reference.path_tracer import PathTracer, ReferenceSettings
from pipeline.scene import find_camera, load_scene
from pipeline.scene.types import Camera, Scene
from pipeline.scenes import SCENES
from pipeline.tracing import Tracer
from relight_torch.cache.layer import read_cache_layer
from relight_torch.direct.relighter import Relighter
from relight_torch.direct.settings import RelightSettings
from relight_torch.io.atomic import atomic_path, write_text_atomic
from relight_torch.metrics import psnr, rel_mse
from relight_torch.multiview.relighter import open_multiview_relighter

TABLE_COLUMNS = (
    "scene",
    "coverage",
    "view",
    "psnr_db",
    "psnr_covered_db",
    "psnr_direct_db",
    "rel_mse",
    "hole_fraction_before",
    "hole_fraction_after",
    "large_holes",
    "rays_ms",
    "correspondence_ms",
    "rerender_ms",
    "rays_cpu_ms",
    "correspondence_cpu_ms",
    "rerender_cpu_ms",
    "rerender_rays",
    "light_edit_ms",
)


def camera_path(scene: Scene, camera: Camera, num_views: int, yaw_degrees: float) -> list[Camera]:
    """`num_views` cameras orbiting the shot camera's centre-pixel point (see the module docstring)."""
    tracer = Tracer(scene.geometry)
    origin = camera.world_from_camera[:3, 3]
    forward = -camera.world_from_camera[:3, 2] / np.linalg.norm(camera.world_from_camera[:3, 2])
    hit = tracer.intersect(origin[None].astype(np.float32), forward[None].astype(np.float32))
    distance = float(hit.distance[0]) if hit.hit[0] else 0.5 * scene.diagonal
    pivot = origin + distance * forward
    up = np.array([0.0, 0.0, 1.0]) if scene.up_axis == "Z" else np.array([0.0, 1.0, 0.0])
    lo, hi = scene.bounds
    cameras = []
    for i, t in enumerate(np.linspace(-1.0, 1.0, num_views)):
        angle = np.radians(yaw_degrees * t)
        c, s = np.cos(angle), np.sin(angle)
        k = np.array([[0, -up[2], up[1]], [up[2], 0, -up[0]], [-up[1], up[0], 0]])
        rotation = np.eye(3) + s * k + (1 - c) * (k @ k)  # Rodrigues, about `up`
        matrix = camera.world_from_camera.copy()
        matrix[:3, :3] = rotation @ matrix[:3, :3]
        matrix[:3, 3] = (
            pivot + rotation @ (origin - pivot) + up * 0.05 * float(np.max(hi - lo)) * np.sin(np.pi * i / num_views)
        )
        cameras.append(dataclasses.replace(camera, world_from_camera=matrix, path=f"{camera.path}.path{i}"))
    return cameras


def _ms(function, repeats: int) -> tuple[float, float]:
    """(median wall ms, median CPU ms of this process, all threads) of `function`, after one warm-up.

    On a shared machine the wall time is an upper bound; the CPU time is the work itself."""
    function()
    watch = Stopwatch()
    for _ in range(repeats):
        with watch.section():
            function()
    return watch.median_ms()


def measure_view(
    scene: Scene, relighter, renderer: FrameRenderer, camera: Camera, reference: np.ndarray | None, repeats: int
) -> dict[str, float]:
    """One path view: accuracy against `reference` (None: none) and timings (repeats 0: none)."""
    frame = renderer.render(camera)
    report = frame.report
    row = {
        "hole_fraction_before": report.hole_fraction_before,
        "hole_fraction_after": report.hole_fraction_after,
        "large_holes": report.num_large_holes,
    }
    if reference is not None:
        s = relighter.supersampling
        height, width = camera.height, camera.width
        found = torch.zeros(height * s * width * s)
        found[relighter.relighter.gbuffer.pixel_index] = 1.0
        empty = torch.ones(height * s * width * s)
        empty[view_points(relighter.caster, relighter.occluder_objects, camera, s).pixel_index] = 0.0
        complete = ((found + empty).reshape(height, s, width, s).amin(dim=(1, 3)) > 0).numpy()
        own = Relighter(
            bake_deep_framebuffer(scene, camera, s).gbuffer,
            relighter.visibility,
            s,
            camera.exposure_scale,
            relighter.settings,
            relighter.object_paths,
        )
        own.set_lights(relighter.lights)
        row |= {
            "psnr_db": psnr(frame.image, reference),
            "rel_mse": rel_mse(frame.image, reference),
            "psnr_covered_db": psnr(frame.image[complete], reference[complete]),
            "psnr_direct_db": psnr(own.render().numpy(), reference),
        }
    if repeats < 1:
        return row
    state = {}

    def rays():
        state["view"] = view_points(
            relighter.caster, relighter.occluder_objects, camera, relighter.supersampling, relighter.corner_normals
        )

    def correspondence():
        relighter.set_view(state["view"], exposure_scale=camera.exposure_scale)

    def rerender():
        relighter.relighter.invalidate()
        relighter.render()

    rays_before = relighter.visibility.num_rays
    for name, function in (("rays", rays), ("correspondence", correspondence), ("rerender", rerender)):
        row[f"{name}_ms"], row[f"{name}_cpu_ms"] = _ms(function, repeats)
    row["rerender_rays"] = (relighter.visibility.num_rays - rays_before) / (repeats + 1)  # warm-up and repeats
    row["light_edit_ms"] = relight_ms(relighter, repeats)
    return row


def cached_reference(tracer: PathTracer, camera: Camera, path: Path) -> np.ndarray:
    """The tracer's image of `camera`, kept in `path` (.npy) for the next run."""
    if path.is_file():
        return np.load(path, allow_pickle=False)
    image = tracer.render(camera).mean
    with atomic_path(path) as temp, open(temp, "wb") as handle:
        np.save(handle, image, allow_pickle=False)
    return image


def run_scene(name: str, args: argparse.Namespace, out: Path) -> tuple[list[SweepRow], list[dict]]:
    shot = SCENES[name].write(out / name)
    scene = load_scene(shot, width=args.width, height=args.height)
    camera = find_camera(scene, SCENES[name].camera)
    path = camera_path(scene, camera, args.views, args.yaw)
    references = [None] * len(path)
    if not args.no_reference:
        tracer = PathTracer(scene, ReferenceSettings(spp=args.spp, max_bounces=0, seed=11))
        stem = f"{args.width}x{args.height}-spp{args.spp}-yaw{args.yaw:g}-of{args.views}"
        references = [
            cached_reference(tracer, view, out / name / f"reference{i}-{stem}.npy") for i, view in enumerate(path)
        ]
    rows, table = [], []
    for coverage in args.coverage:
        settings = PlacementSettings(coverage=coverage, max_resolution=args.caching_resolution)
        start = time.perf_counter()
        folder = out / name / f"coverage{coverage:g}"
        layer = (
            reusable_bake(
                folder / f"{name}.relight.usda",
                "multiview",
                (args.width, args.height),
                args.supersampling,
                {"maxResolution": args.caching_resolution, "coverage": coverage},
            )
            if args.reuse_bake
            else None
        )
        bake_s = float("nan")
        if layer is None:
            layer = bake_multiview(scene, camera, folder, name, args.supersampling, settings=settings)
            bake_s = time.perf_counter() - start
        parameters = read_cache_layer(layer).parameters
        relighter = open_multiview_relighter(
            layer,
            settings=RelightSettings(area_samples=args.area_samples),
            sample_groups=args.sample_groups,
            blend_lighting=args.blend_lighting,
            edge_contrast=args.edge_contrast,
            near_field=args.near_field,
        )
        relighter.caster.num_threads = args.threads  # the shadow rays' caster too
        renderer = FrameRenderer(relighter, fill_holes=args.fill_holes)
        start = time.perf_counter()
        relighter.prepare_lighting()
        print(
            f"{name} coverage {coverage:g}: lighting of {relighter.views.pool.num_samples} caching samples traced "
            f"in {time.perf_counter() - start:.1f} s ({relighter.lighting_bytes() / 1e6:.0f} MB)",
            file=sys.stderr,
        )
        views = []
        for i, (view, reference) in enumerate(zip(path, references, strict=True)):
            measured = measure_view(scene, relighter, renderer, view, reference, args.repeats)
            views.append(measured)
            table.append({"scene": name, "coverage": coverage, "view": i} | measured)
            print(
                f"{name} coverage {coverage:g} view {i}: " + " ".join(f"{k}={v:.4g}" for k, v in measured.items()),
                file=sys.stderr,
            )
        mean = {key: float(np.mean([v[key] for v in views])) for key in ("psnr_db", "rel_mse") if key in views[0]}
        rows.append(
            SweepRow(
                method="multiview",
                scene=name,
                width=args.width,
                height=args.height,
                light_edit="shot",
                params=format_params(
                    {
                        "coverage": coverage,
                        "cameras": parameters["numViews"],
                        "primary": parameters["numPrimary"],
                        "secondary": parameters["numSecondary"],
                        "uncovered": round(parameters["uncoveredFraction"], 4),
                        "maxResolution": args.caching_resolution,
                        "views": args.views,
                        "supersampling": args.supersampling,
                        "fillHoles": int(args.fill_holes),
                        "areaSamples": args.area_samples,
                        "sampleGroups": args.sample_groups,
                        "blendLighting": int(args.blend_lighting),
                        "edgeContrast": "none" if args.edge_contrast is None else args.edge_contrast,
                        "nearField": "none" if args.near_field is None else args.near_field,
                    }
                ),
                psnr_db=mean.get("psnr_db", float("nan")),
                rel_mse=mean.get("rel_mse", float("nan")),
                cache_bytes=float(cache_bytes(layer)),
                bake_s=bake_s,
                relight_ms=float(np.median([v.get("light_edit_ms", float("nan")) for v in views])),
            )
        )
    return rows, table


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes", nargs="+", choices=sorted(SCENES))
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--views", type=int, default=8, help="novel views on the path (default 8)")
    parser.add_argument("--yaw", type=float, default=20.0, help="path yaw range +-degrees (default 20)")
    parser.add_argument("--coverage", type=float, nargs="+", default=[0.1, 0.05, 0.02])
    parser.add_argument("--caching-resolution", type=int, default=512)
    parser.add_argument("--supersampling", type=int, default=1)
    parser.add_argument("--spp", type=int, default=16, help="reference samples per pixel (default 16)")
    parser.add_argument(
        "--area-samples",
        type=int,
        default=RelightSettings().area_samples,
        help="relighter samples per area light and point (default: the relighter's)",
    )
    parser.add_argument(
        "--sample-groups",
        type=int,
        default=1,
        help="light-sample groups whose BRDF a view evaluates together (default 1)",
    )
    parser.add_argument(
        "--blend-lighting",
        action="store_true",
        help="blend the cached lighting of the four caching pixels (default: the nearest)",
    )
    parser.add_argument(
        "--edge-contrast",
        type=lambda v: None if v == "none" else float(v),
        default=0.8,
        help="trace a light again at view points on its edges in the caching images "
        "(contrast of the caching taps' fractions of the light reaching them, and of "
        "their unshadowed light; default 0.8; 'none': a camera move traces nothing)",
    )
    parser.add_argument(
        "--near-field",
        type=lambda v: None if v == "none" else float(v),
        default=0.1,
        help="trace a light again at view points farther from their caching sample than this "
        "fraction of their distance to the light (default 0.1; 'none': never)",
    )
    parser.add_argument("--threads", type=int, default=2, help="torch and Embree threads (default 2)")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per median; 0: no timings")
    parser.add_argument("--fill-holes", action="store_true", help="bake large holes on demand")
    parser.add_argument("--no-reference", action="store_true", help="timings only")
    parser.add_argument(
        "--reuse-bake",
        action="store_true",
        help="open the cache an earlier run baked in OUT with the same settings (bake_s NaN)",
    )
    parser.add_argument("--out", type=Path, default=Path("multiview_path"))
    parser.add_argument("--csv", type=Path, help="shared sweep CSV (default OUT/multiview.csv)")
    parser.add_argument("--table", type=Path, help="per-view CSV (default OUT/multiview_views.csv)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    rows, table = [], []
    for name in args.scenes:
        scene_rows, scene_table = run_scene(name, args, args.out)
        rows += scene_rows
        table += scene_table
    write_csv(rows, args.csv or args.out / "multiview.csv")
    text = io.StringIO()
    writer = csv.DictWriter(text, TABLE_COLUMNS, restval="nan", lineterminator="\n")
    writer.writeheader()
    writer.writerows(table)
    write_text_atomic(args.table or args.out / "multiview_views.csv", text.getvalue())
    return 0


if __name__ == "__main__":
    sys.exit(main())
