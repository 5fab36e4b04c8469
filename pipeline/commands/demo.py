"""`relight demo`: the README's first command — bake a bundled scene's shot cache, relight it, compare.

Writes into OUT: the bundled scene, its example light edits and a new sphere light; the shot cache
(the default bake: direct and bounce light, sized by measurement against the full frame); for the
shot's own lights and each edit, the relit EXR and PNG, the path tracer's full frame (every bounce,
same lights layer) EXR and PNG, and their PSNR and energy ratio; `chart.png` plotting relight time
against accuracy next to the path tracer's time; `summary.csv`.
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np

from pipeline.bake.shot import DEFAULT_TARGET_DB, bake_shot
from pipeline.commands.common import add_device_option
from pipeline.errors import RelightError
from pipeline.reference.path_tracer import FULL_FRAME_BOUNCES, PathTracer, ReferenceSettings
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES, light_edit_layers
from pipeline.scenes.lights import new_sphere_layer
from pipeline.tracing_bench import median_seconds
from relight_torch import open_cache
from relight_torch.cache.layer import read_cache_layer
from relight_torch.direct.loading import shot_lights
from relight_torch.io.atomic import atomic_path
from relight_torch.io.exr import write_rgb_exr
from relight_torch.io.preview import write_png
from relight_torch.metrics import psnr


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "demo",
        help="bake a bundled scene, relight it under light edits, compare with the reference",
        description=__doc__.split("\n\n")[1],
    )
    parser.add_argument("--out", "-o", default="out/demo", metavar="DIR", help="output directory (default out/demo)")
    parser.add_argument(
        "--scene", default="cornell_box", choices=sorted(SCENES), help="bundled scene (default cornell_box)"
    )
    parser.add_argument("--width", type=int, default=160, metavar="W", help="image width (default 160)")
    parser.add_argument("--height", type=int, default=160, metavar="H", help="image height (default 160)")
    parser.add_argument("--spp", type=int, default=256, help="reference samples per pixel (default 256)")
    parser.add_argument(
        "--quality",
        type=float,
        default=DEFAULT_TARGET_DB,
        metavar="PSNR",
        help=f"the shot cache's quality target against the full frame (default {DEFAULT_TARGET_DB:g})",
    )
    add_device_option(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    if args.spp < 1:
        raise RelightError(f"--spp must be >= 1, got {args.spp}")
    out = Path(args.out)
    bundled = SCENES[args.scene]
    shot = bundled.write(out / "scene")
    edits = list(light_edit_layers(args.scene, out / "scene").items())
    edits.append(
        ("new_light", new_sphere_layer(shot, bundled.camera, out / "scene" / f"{args.scene}.lights.new_light.usda"))
    )
    scene = load_scene(shot, width=args.width, height=args.height)
    camera = find_camera(scene, bundled.camera)
    start = time.perf_counter()
    choice, result = bake_shot(scene, camera, out / "cache", args.scene, args.quality)
    bake_seconds = time.perf_counter() - start
    print(
        f"baked the shot cache {result.layer} ({choice.components}, {choice.bounces} bounces, {result.point}) "
        f"in {bake_seconds:.1f} s: {result.measured_db:.1f} dB against the full frame"
    )
    relighter = open_cache(result.layer, device=args.device)
    description = read_cache_layer(result.layer)
    rows = []
    for name, layer in edits:
        lights = shot_lights(description, layer)
        start = time.perf_counter()
        relighter.set_lights(lights)
        image = relighter.render()
        edit_ms = (time.perf_counter() - start) * 1e3
        warm_ms = median_seconds(relighter.render, repeats=5) * 1e3
        image = image.cpu().numpy()
        reference_scene = load_scene(shot, lights_layer=layer, width=args.width, height=args.height)
        tracer = PathTracer(reference_scene, ReferenceSettings(spp=args.spp, max_bounces=FULL_FRAME_BOUNCES))
        reference = tracer.render(find_camera(reference_scene, bundled.camera))
        write_rgb_exr(out / f"{name}.relit.exr", image)
        write_png(out / f"{name}.relit.png", image)
        write_rgb_exr(out / f"{name}.reference.exr", reference.mean)
        write_png(out / f"{name}.reference.png", reference.mean)
        rows.append(
            {
                "edit": name,
                "edit_ms": edit_ms,
                "render_ms": warm_ms,
                "reference_s": reference.seconds,
                "reference_spp": args.spp,
                "psnr_db": psnr(image, reference.mean),
                "energy_ratio": float(image.mean() / reference.mean.mean()),
            }
        )
        print(
            f"{name:>12}: edit {edit_ms:8.1f} ms, re-render {warm_ms:6.1f} ms, reference "
            f"{reference.seconds:6.1f} s at {args.spp} spp, PSNR {rows[-1]['psnr_db']:.1f} dB, "
            f"energy ratio {rows[-1]['energy_ratio']:.3f}"
        )
    with atomic_path(out / "summary.csv") as temp, open(temp, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    _chart(out / "chart.png", rows, args)
    print(f"images, summary.csv and chart.png in {out}")
    return 0


def _chart(path: Path, rows: list[dict], args: argparse.Namespace) -> None:
    """Relight time against PSNR per edit, with the reference's time for scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(7, 4.5), dpi=120)
    for row in rows:
        points = axes.scatter(row["edit_ms"], row["psnr_db"], label=f"{row['edit']}: apply the edit")
        axes.scatter(
            row["render_ms"],
            row["psnr_db"],
            marker="x",
            color=points.get_facecolor(),
            label=f"{row['edit']}: re-render, nothing changed",
        )
        axes.annotate(row["edit"], (row["edit_ms"], row["psnr_db"]), textcoords="offset points", xytext=(5, 5))
    reference_ms = np.median([r["reference_s"] for r in rows]) * 1e3
    axes.axvline(reference_ms, color="grey", linestyle="--", label=f"reference render ({args.spp} spp)")
    axes.set_xscale("log")
    axes.set_xlabel("milliseconds per frame (log)")
    axes.set_ylabel("PSNR against the path tracer's full frame (dB)")
    axes.set_title(f"{args.scene} {args.width}x{args.height}: shot-cache relighting vs re-rendering")
    axes.legend(fontsize=7, loc="lower left", ncol=2)
    axes.grid(True, which="both", alpha=0.3)
    figure.tight_layout()
    with atomic_path(path) as temp:
        figure.savefig(temp, format="png")
    plt.close(figure)
