"""`relight bake`: bake a shot's relighting cache."""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from pipeline.bake import scheduler
from pipeline.bake.cuts.bake import MODES as CUTS_MODES
from pipeline.bake.cuts.bake import CutsSettings, bake_cuts
from pipeline.bake.direct import bake_direct
from pipeline.bake.inputs import record_request, request_digest, up_to_date
from pipeline.bake.gather.bake import GatherSettings, bake_gather
from pipeline.bake.quality import bake_for_quality
from pipeline.bake.multiview.bake import bake_multiview, coverage_summary
from pipeline.bake.multiview.placement import PlacementSettings
from pipeline.bake.transfer.bake import TransferSettings, bake_transfer, reduced_view
from pipeline.commands.common import add_camera_options
from pipeline.errors import RelightError
from pipeline.scene import find_camera, load_scene
from relight_torch.cache.layer import SUFFIX

METHODS = ("direct", "transfer", "gather", "multiview", "cuts")
DEFAULT_SUPERSAMPLING = {"transfer": 1, "gather": 1}
"""Methods baked at one sub-sample per pixel unless --supersampling says otherwise (2 for the rest):
their relight cost grows with the sub-samples and their error lies mostly in the indirect light, not
in the edges' aliasing (docs/ACCURACY.md, 'Size-aware defaults')."""


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "bake", help="bake a relighting cache for a shot and camera",
        description="Trace the shot once and write OUT/<stem>.relight.usda with its payload files "
                    "(deep framebuffer EXR, occluders). Files are written atomically.")
    parser.add_argument("scene", metavar="SCENE", help="USD stage (.usda, .usdc, .usdz)")
    add_camera_options(parser)
    parser.add_argument("--out", "-o", required=True, metavar="DIR", help="output directory")
    parser.add_argument("--method", default="direct", choices=METHODS,
                        help="relighting method to bake for (default: direct)")
    parser.add_argument("--supersampling", type=int, metavar="S",
                        help="S x S sub-samples per pixel, shaded separately and box-filtered (default 2; 1 for "
                             "transfer and gather, whose every edit costs S^2 and whose error is mostly indirect light)")
    parser.add_argument("--texture-samples", type=int, default=4, metavar="T",
                        help="up to T x T material samples per sub-sample, averaged: texture and normal-map "
                             "filtering; 2 x 2 where materials are constant (default 4)")
    parser.add_argument("--stem", help="file name stem (default: the scene file's stem)")
    parser.add_argument("--quality", type=float, metavar="PSNR",
                        help="size the method (supersampling; gathers and coefficients; clusters and representatives) "
                             "for this PSNR in dB against the path tracer, from pilot bakes at a small size; the "
                             "choice and the predicted and measured PSNR go into the cache (overrides those options)")
    parser.add_argument("--scheduler", metavar="ADDRESS",
                        help="run the bake's chunks on a Dask cluster: tcp://HOST:PORT, or 'dask' for the address "
                             "in Dask's configuration (default: this machine; see docs/DISTRIBUTED.md)")
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help="local worker processes for the chunks (default: this process, all CPUs as threads)")
    transfer = parser.add_argument_group("transfer (--method transfer)")
    defaults = TransferSettings()
    transfer.add_argument("--gathers", type=int, default=defaults.num_gathers, metavar="G",
                          help=f"gather samples, a power of 4 (default {defaults.num_gathers})")
    transfer.add_argument("--coefficients", type=int, default=defaults.num_coefficients, metavar="K",
                          help=f"wavelet coefficients kept per final-gather row (default {defaults.num_coefficients})")
    transfer.add_argument("--bounces", type=int, default=defaults.num_bounces, metavar="B",
                          help="indirect bounces; 1 bakes the final gather only (default 1)")
    transfer.add_argument("--bounce-coefficients", type=int, default=defaults.num_bounce_coefficients, metavar="K",
                          help=f"coefficients kept per gather-to-gather row (default {defaults.num_bounce_coefficients})")
    transfer.add_argument("--quantize", action="store_true",
                          help="store coefficients as 8 bits with a per-row scale and offset (default float16)")
    transfer.add_argument("--indirect-scale", type=int, default=defaults.indirect_scale, metavar="S",
                          help="bake the final gather for an image S times smaller per side, upsampled edge-aware "
                               "at relight time (S must divide the width and height; default 2 from 240 pixels on "
                               "the shorter side, else 1)")
    gather = parser.add_argument_group("gather (--method gather)")
    gather_defaults = GatherSettings()
    gather.add_argument("--directions", type=int, default=gather_defaults.num_directions, metavar="N",
                        help=f"QMC hemisphere directions per view representative (default {gather_defaults.num_directions})")
    gather.add_argument("--clusters", type=int, default=gather_defaults.num_clusters, metavar="K",
                        help=f"clustered gathers per view representative (default {gather_defaults.num_clusters})")
    gather.add_argument("--representatives", type=int, default=None, metavar="R",
                        help="view representatives (default: 40,000 at 400x400, scaled with the pixel count)")
    gather.add_argument("--point-cells", type=int, default=gather_defaults.point_cells, metavar="C",
                        help="cells across the scene diagonal of the grid the clustered gathers share lit surface "
                             f"points on; 0 shares identical points only (default {gather_defaults.point_cells})")
    multiview = parser.add_argument_group("multiview (--method multiview)")
    multiview_defaults = PlacementSettings()
    multiview.add_argument("--coverage", type=float, default=multiview_defaults.coverage, metavar="F",
                           help="add caching cameras until less than this fraction of the surfaces' importance is "
                                f"uncovered (default {multiview_defaults.coverage})")
    multiview.add_argument("--box", type=float, nargs=6, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
                           help="workspace box for the caching cameras (default: the scene's bounds)")
    multiview.add_argument("--caching-resolution", type=int, default=multiview_defaults.max_resolution, metavar="R",
                           help=f"largest caching image side (default {multiview_defaults.max_resolution})")
    cuts = parser.add_argument_group("cuts (--method cuts)")
    cuts_defaults = CutsSettings()
    cuts.add_argument("--mode", default=cuts_defaults.mode, choices=CUTS_MODES,
                      help="light points: 'env' = directions on the sphere (dome lights), 'indirect' = surface "
                           "points (one diffuse bounce of every light; --cut-lights a power of 4) (default env)")
    cuts.add_argument("--cut-lights", type=int, default=cuts_defaults.num_lights, metavar="L",
                      help=f"point lights in the light tree, a power of two (default {cuts_defaults.num_lights})")
    cuts.add_argument("--sigma", type=float, default=cuts_defaults.sigma, metavar="SIGMA",
                      help=f"visibility cut threshold |C| var <= SIGMA^2 (default {cuts_defaults.sigma})")
    cuts.add_argument("--lattice-edge", type=float, default=cuts_defaults.lattice_edge, metavar="F",
                      help="longest edge of the refined triangles carrying visibility cuts, as a fraction of the "
                           f"scene diagonal (default {cuts_defaults.lattice_edge:.4g})")
    cuts.add_argument("--beta", type=float, default=cuts_defaults.beta, metavar="B",
                      help="data-driven light tree: blend of geometric and pilot-visibility distances, "
                           "0.4-0.5 in the paper (default 1: geometric only)")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    if args.supersampling is None:
        args.supersampling = DEFAULT_SUPERSAMPLING.get(args.method, 2)
    if args.supersampling < 1 or args.texture_samples < 1:
        raise RelightError(f"--supersampling and --texture-samples must be >= 1, "
                           f"got {args.supersampling} and {args.texture_samples}")
    if args.workers is not None and args.workers < 1:
        raise RelightError(f"--workers must be >= 1, got {args.workers}")
    with scheduler.using(scheduler.Scheduler(address=args.scheduler, workers=args.workers)):
        return _bake(args)


def _check(method: str, *checks: Callable[[], object]) -> None:
    """Run the method's settings checks; a ValueError becomes one `bake --method` error line."""
    try:
        for check in checks:
            check()
    except ValueError as error:
        raise RelightError(f"bake --method {method}: {error}") from None


_NOT_REQUEST = ("out", "stem", "scheduler", "workers")
"""Options that do not change the cache (where and how it is computed)."""


def _bake(args: argparse.Namespace) -> int:
    stem = args.stem or Path(args.scene).name.split(".")[0]
    layer_path = Path(args.out) / f"{stem}{SUFFIX}"
    request = {name: value for name, value in vars(args).items()
               if name not in _NOT_REQUEST and isinstance(value, (str, int, float, bool, list, tuple, type(None)))}
    digest = request_digest({**request, "scene": str(Path(args.scene).resolve())})
    if up_to_date(layer_path, digest):
        print(f"{layer_path}: up to date (same request, inputs and code; payloads verified), nothing baked")
        return 0
    record_request(_bake_method(args, stem), digest)
    return 0


def _fixed_sizes(args: argparse.Namespace) -> dict[str, object] | None:
    """The options `--quality` keeps as given while it sizes the rest (see `bake_for_quality`)."""
    return {"transfer": {"bounces": args.bounces}, "cuts": {"mode": args.mode}}.get(args.method)


def _bake_method(args: argparse.Namespace, stem: str) -> Path:
    """Run the bake `args` asks for; the cache layer's path."""
    start = time.perf_counter()
    scene = load_scene(args.scene, time=args.time, width=args.width, height=args.height)
    camera = find_camera(scene, args.camera)
    if args.quality is not None:
        result = bake_for_quality(scene, camera, args.out, stem, args.method, args.quality, args.supersampling,
                                  args.texture_samples, args.time,
                                  fixed=_fixed_sizes(args))
        print(f"{result.layer}: {args.method} cache sized for {args.quality:g} dB: {result.point} (pilot "
              f"{result.predicted_db:.1f} dB, measured {result.measured_db:.1f} dB) in {time.perf_counter() - start:.1f} s")
        return result.layer
    if args.method == "transfer":
        settings = TransferSettings(num_gathers=args.gathers, num_coefficients=args.coefficients,
                                    num_bounces=args.bounces, num_bounce_coefficients=args.bounce_coefficients,
                                    encoding="uint8" if args.quantize else "float16",
                                    indirect_scale=args.indirect_scale)
        _check("transfer", settings.check, lambda: reduced_view(scene, camera, settings.for_view(camera).indirect_scale))
        layer = bake_transfer(scene, camera, args.out, stem, args.supersampling, args.texture_samples,
                              time_code=args.time, settings=settings)
    elif args.method == "gather":
        settings = GatherSettings(num_directions=args.directions, num_clusters=args.clusters,
                                  num_representatives=args.representatives, point_cells=args.point_cells)
        _check("gather", settings.check)
        layer = bake_gather(scene, camera, args.out, stem, args.supersampling, args.texture_samples,
                            time_code=args.time, settings=settings)
    elif args.method == "multiview":
        settings = PlacementSettings(coverage=args.coverage, max_resolution=args.caching_resolution,
                                     min_resolution=min(PlacementSettings().min_resolution, args.caching_resolution))
        _check("multiview", settings.check)
        box = None if args.box is None else (np.array(args.box[:3]), np.array(args.box[3:]))
        if box is not None and not np.all(box[0] < box[1]):
            raise RelightError(f"bake --box: need X0 < X1, Y0 < Y1, Z0 < Z1, got {args.box}")
        layer = bake_multiview(scene, camera, args.out, stem, args.supersampling, args.texture_samples,
                               time_code=args.time, settings=settings, box=box)
        print(coverage_summary(layer))
    elif args.method == "cuts":
        settings = CutsSettings(mode=args.mode, num_lights=args.cut_lights, sigma=args.sigma,
                                lattice_edge=args.lattice_edge, beta=args.beta)
        _check("cuts", settings.check)
        layer = bake_cuts(scene, camera, args.out, stem, args.supersampling, args.texture_samples,
                          time_code=args.time, settings=settings)
    else:
        layer = bake_direct(scene, camera, args.out, stem, args.supersampling, args.texture_samples,
                            time_code=args.time)
    print(f"{layer}: {args.method} cache of {args.camera} at {camera.width}x{camera.height} "
          f"(supersampling {args.supersampling}) in {time.perf_counter() - start:.1f} s")
    return layer
