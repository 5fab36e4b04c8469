"""`relight bake`: bake a shot's relighting cache."""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

from pipeline.bake import scheduler
from pipeline.bake.inputs import record_request, request_digest, up_to_date
from pipeline.bake.methods import bake_method, bake_methods
from pipeline.bake.quality import bake_for_quality
from pipeline.bake.shot import DEFAULT_TARGET_DB, bake_shot
from pipeline.bake.staging import commit_staged, staged_bake
from pipeline.commands.common import add_camera_options
from pipeline.errors import RelightError
from pipeline.scene import find_camera, load_scene
from relight_torch.cache.layer import SUFFIX


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "bake",
        help="bake a relighting cache for a shot and camera",
        description="Trace the shot once and write OUT/<stem>.relight.usda with its payload files "
        "(deep framebuffer EXR, occluders). The bake runs in OUT/.<stem>.staging and replaces an older "
        "cache only once it has finished; files are written atomically.",
    )
    parser.add_argument("scene", metavar="SCENE", help="USD stage (.usda, .usdc, .usdz)")
    add_camera_options(parser)
    parser.add_argument("--out", "-o", required=True, metavar="DIR", help="output directory")
    methods = bake_methods()
    parser.add_argument(
        "--method",
        choices=list(methods),
        help="bake one relighting method alone (default: the shot cache, whose components, "
        "bounces and sizes pilot bakes choose to match the full frame to --quality)",
    )
    single = [name for name, method in methods.items() if method.default_supersampling == 1]
    parser.add_argument(
        "--supersampling",
        type=int,
        metavar="S",
        help=f"S x S sub-samples per pixel, shaded separately and box-filtered (default 2; 1 for "
        f"{' and '.join(single)}, whose every edit costs S^2 and whose error is mostly indirect "
        f"light)",
    )
    parser.add_argument(
        "--texture-samples",
        type=int,
        default=4,
        metavar="T",
        help="up to T x T material samples per sub-sample, averaged: texture and normal-map "
        "filtering; 2 x 2 where materials are constant (default 4)",
    )
    parser.add_argument("--stem", help="file name stem (default: the scene file's stem)")
    parser.add_argument(
        "--quality",
        type=float,
        metavar="PSNR",
        help="PSNR in dB against the path tracer that pilot bakes at a small size size the cache "
        f"for (the shot cache: default {DEFAULT_TARGET_DB:g} against the full frame; with "
        "--method: that method's sizes against its own slice, overriding their options); the "
        "choice and the predicted and measured PSNR go into the cache",
    )
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="run the bake's chunks on a Dask cluster: tcp://HOST:PORT, or 'dask' for the address "
        "in Dask's configuration (default: this machine; see docs/DISTRIBUTED.md)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="local worker processes for the chunks (default: this process, all CPUs as threads)",
    )
    for method in methods.values():
        method.add_options(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    if args.method is None and args.quality is None:
        args.quality = DEFAULT_TARGET_DB
    if args.supersampling is None:
        args.supersampling = 2 if args.method is None else bake_method(args.method).default_supersampling
    if args.supersampling < 1 or args.texture_samples < 1:
        raise RelightError(
            f"--supersampling and --texture-samples must be >= 1, got {args.supersampling} and {args.texture_samples}"
        )
    if args.workers is not None and args.workers < 1:
        raise RelightError(f"--workers must be >= 1, got {args.workers}")
    with scheduler.using(scheduler.Scheduler(address=args.scheduler, workers=args.workers)):
        return _bake(args)


_NOT_REQUEST = ("out", "stem", "scheduler", "workers")
"""Options that do not change the cache (where and how it is computed)."""


def _bake(args: argparse.Namespace) -> int:
    stem = args.stem or Path(args.scene).name.split(".")[0]
    layer_path = Path(args.out) / f"{stem}{SUFFIX}"
    request = {
        name: value
        for name, value in vars(args).items()
        if name not in _NOT_REQUEST and isinstance(value, (str, int, float, bool, list, tuple, type(None)))
    }
    digest = request_digest({**request, "scene": str(Path(args.scene).resolve())})
    if up_to_date(layer_path, digest):
        print(f"{layer_path}: up to date (same request, inputs and code; payloads verified), nothing baked")
        return 0
    # Baked aside and committed only when finished: a failed re-bake leaves the old cache usable.
    with staged_bake(args.out, stem) as staging:
        staged, summary = _bake_method(args, stem, staging)
        record_request(staged, digest)
        layer_path = commit_staged(staged, Path(args.out))
    print(f"{layer_path}: {summary}")
    return 0


def _bake_method(args: argparse.Namespace, stem: str, out: Path) -> tuple[Path, str]:
    """Run the bake `args` asks for into `out`; the cache layer's path and a summary line."""
    start = time.perf_counter()
    scene = load_scene(args.scene, time=args.time, width=args.width, height=args.height)
    camera = find_camera(scene, args.camera)
    if args.method is None:
        choice, result = bake_shot(scene, camera, out, stem, args.quality, args.texture_samples, args.time)
        return result.layer, (
            f"shot cache ({choice.components}, {choice.bounces} bounces, {result.point}) for "
            f"{args.quality:g} dB against the full frame: pilot {_pilot(result.predicted_db)}, measured "
            f"{result.measured_db:.1f} dB, in {time.perf_counter() - start:.1f} s"
        )
    method = bake_method(args.method)
    if args.quality is not None:
        result = bake_for_quality(
            scene,
            camera,
            out,
            stem,
            args.method,
            args.quality,
            args.supersampling,
            args.texture_samples,
            args.time,
            fixed=method.quality_fixed(args) if method.quality_fixed else None,
        )
        return result.layer, (
            f"{args.method} cache sized for {args.quality:g} dB: {result.point} (pilot "
            f"{_pilot(result.predicted_db)}, measured {result.measured_db:.1f} dB) "
            f"in {time.perf_counter() - start:.1f} s"
        )
    settings = method.settings_from_args(args, scene, camera)
    layer = method.bake(scene, camera, out, stem, args.supersampling, args.texture_samples, args.time, settings)
    if method.report is not None:
        print(method.report(layer))
    return layer, (
        f"{args.method} cache of {args.camera} at {camera.width}x{camera.height} "
        f"(supersampling {args.supersampling}) in {time.perf_counter() - start:.1f} s"
    )


def _pilot(predicted_db: float) -> str:
    """The pilot's PSNR in words: none for a size the full-size check reached without the pilot."""
    return "not baked (chosen at full size)" if math.isnan(predicted_db) else f"{predicted_db:.1f} dB"
