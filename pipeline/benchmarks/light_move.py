"""Speed and accuracy of moving one light in the direct relighter: the lighting artist's main edit.

    python -m pipeline.benchmarks.light_move CACHE [--light PRIM] [--repeats N] [--reference REF.exr]
        [--area-samples S] [--filtered-samples F] [--filter-radius R] [--profile N] [--threads T]

Opens CACHE with the shot's lights and renders the first frame; with `--reference` (a
`relight reference --max-bounces 0` render of the same shot, camera and size) prints its PSNR,
relMSE and energy ratio against it. Then moves one light (`--light`, default the shot's first
SphereLight) `repeats` times by a few centimetres, each move followed by `render()`, and prints
the median wall and CPU milliseconds per move. `--profile N` also prints the N functions with the
most cumulative time over the moves (cProfile, which sees the calling thread only: profile with
`--threads 1`, which runs torch and the relighter's tiles on that thread). On a shared machine the
wall times count other people's work; the CPU times do not.
"""

from __future__ import annotations

import argparse
import cProfile
import dataclasses
import io
import pstats

import numpy as np
import torch

from pipeline.benchmarks.stopwatch import Stopwatch
from relight_torch.direct.relighter import open_relighter
from relight_torch.direct.settings import RelightSettings
from relight_torch.io.exr import read_rgb_exr
from relight_torch.lights.light import LightKind
from relight_torch.metrics import psnr, rel_mse


def accuracy(image: torch.Tensor, reference_path: str) -> dict[str, float]:
    """PSNR, relMSE and energy ratio of an (H, W, 3) image against a reference EXR's RGB."""
    reference = read_rgb_exr(reference_path).astype(np.float64)
    ours = image.double().numpy()
    if reference.shape != ours.shape:
        raise SystemExit(f"light_move: reference {reference.shape} does not match the cache's image {ours.shape}")
    return {
        "psnr_db": psnr(ours, reference),
        "rel_mse": rel_mse(ours, reference),
        "energy_ratio": float(ours.mean() / reference.mean()),
    }


def measure(args: argparse.Namespace) -> dict[str, object]:
    """The figures of the module doc."""
    settings = RelightSettings()
    overrides = {
        "area_samples": args.area_samples,
        "filtered_area_samples": args.filtered_samples,
        "shadow_filter_radius": args.filter_radius,
    }
    settings = dataclasses.replace(settings, **{k: v for k, v in overrides.items() if v is not None})
    settings = dataclasses.replace(settings, shared_lighting=args.shared_lighting)
    first, moves = Stopwatch(), Stopwatch()
    with first.section():
        relighter = open_relighter(args.cache, settings=settings)
        image = relighter.render()
    figures: dict[str, object] = {}
    height, width = image.shape[:2]
    figures["image"] = f"{width}x{height}"
    figures["sub_samples"] = relighter.gbuffer.num_samples
    figures["lights"] = len(relighter.lights)
    figures["open_and_first_frame_s"] = first.wall[0]
    if args.reference:
        figures.update(accuracy(image, args.reference))
    lights = {light.path: light for light in relighter.lights}
    path = args.light or next((p for p, light in lights.items() if light.kind is LightKind.SPHERE), None)
    if path not in lights:
        raise SystemExit(f"light_move: no light {path!r} in the cache's shot (has {sorted(lights)})")
    light = lights[path]
    figures["light"] = path
    rng = np.random.default_rng(0)
    profiler = cProfile.Profile() if args.profile else None
    for _ in range(args.repeats):
        transform = light.world_from_light.copy()
        transform[:3, 3] += rng.uniform(-0.05, 0.05, 3)
        light = dataclasses.replace(light, world_from_light=transform)
        with moves.section():
            if profiler is not None:
                profiler.enable()
            relighter.set_light(light)
            relighter.render()
            if profiler is not None:
                profiler.disable()
    figures["move_ms"], figures["move_cpu_ms"] = moves.median_ms()
    figures["move_ms_all"] = " ".join(f"{1e3 * t:.0f}" for t in moves.wall)
    if profiler is not None:
        text = io.StringIO()
        pstats.Stats(profiler, stream=text).sort_stats("cumulative").print_stats(args.profile)
        figures["profile"] = "\n" + text.getvalue()
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("cache")
    parser.add_argument("--light", metavar="PRIM", help="the light to move (default: the first SphereLight)")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--reference", metavar="REF.exr", help="direct-light reference of the same shot and size")
    parser.add_argument("--area-samples", type=int, help="RelightSettings.area_samples")
    parser.add_argument("--filtered-samples", type=int, help="RelightSettings.filtered_area_samples")
    parser.add_argument("--filter-radius", type=int, help="RelightSettings.shadow_filter_radius")
    parser.add_argument(
        "--shared-lighting",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="RelightSettings.shared_lighting (default: on)",
    )
    parser.add_argument("--profile", type=int, default=0, metavar="N", help="print the N costliest functions")
    parser.add_argument("--threads", type=int, metavar="T", help="torch threads (default: torch's own count)")
    args = parser.parse_args()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    for name, value in measure(args).items():
        print(f"{name}: {value:.4g}" if isinstance(value, float) else f"{name}: {value}")


if __name__ == "__main__":
    main()
