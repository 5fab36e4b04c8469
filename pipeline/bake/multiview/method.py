"""The 'multiview' method's bake-side registry entry (`pipeline.bake.methods`)."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.bake.methods import BakeMethod, checked
from pipeline.bake.multiview.adapter import ADAPTER
from pipeline.bake.multiview.bake import bake_multiview, coverage_summary
from pipeline.bake.multiview.frames import render_frames
from pipeline.bake.multiview.placement import PlacementSettings
from pipeline.errors import RelightError
from pipeline.scene.types import Camera, Scene
from relight_torch.multiview.method import METHOD as RELIGHT
from relight_torch.multiview.relighter import MultiviewRelighter


@dataclass(frozen=True)
class MultiviewBakeSettings:
    """The caching cameras' placement and the workspace box they are placed in (None: the scene's bounds)."""

    placement: PlacementSettings
    box: tuple[np.ndarray, np.ndarray] | None = None


def add_options(parser: argparse.ArgumentParser) -> None:
    """The `relight bake` options of the multiview method."""
    multiview = parser.add_argument_group("multiview (--method multiview)")
    multiview_defaults = PlacementSettings()
    multiview.add_argument(
        "--coverage",
        type=float,
        default=multiview_defaults.coverage,
        metavar="F",
        help="add caching cameras until less than this fraction of the surfaces' importance is "
        f"uncovered (default {multiview_defaults.coverage})",
    )
    multiview.add_argument(
        "--box",
        type=float,
        nargs=6,
        metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
        help="workspace box for the caching cameras (default: the scene's bounds)",
    )
    multiview.add_argument(
        "--caching-resolution",
        type=int,
        default=multiview_defaults.max_resolution,
        metavar="R",
        help=f"largest caching image side (default {multiview_defaults.max_resolution})",
    )


def settings_from_args(args: argparse.Namespace, scene: Scene, camera: Camera) -> MultiviewBakeSettings:
    """The placement settings and box the options ask for, checked."""
    settings = PlacementSettings(
        coverage=args.coverage,
        max_resolution=args.caching_resolution,
        min_resolution=min(PlacementSettings().min_resolution, args.caching_resolution),
    )
    checked("multiview", settings.check)
    box = None if args.box is None else (np.array(args.box[:3]), np.array(args.box[3:]))
    if box is not None and not np.all(box[0] < box[1]):
        raise RelightError(f"bake --box: need X0 < X1, Y0 < Y1, Z0 < Z1, got {args.box}")
    return MultiviewBakeSettings(settings, box)


def _bake(
    scene: Scene,
    camera: Camera,
    out_dir: Path,
    stem: str,
    supersampling: int,
    texture_samples: int,
    time_code: float | None,
    settings: MultiviewBakeSettings,
) -> Path:
    return bake_multiview(
        scene,
        camera,
        out_dir,
        stem,
        supersampling,
        texture_samples,
        time_code=time_code,
        settings=settings.placement,
        box=settings.box,
    )


def render_views(relighter: MultiviewRelighter, args: argparse.Namespace, layers: Callable | None) -> None:
    """`relight render` of a multiview cache: one frame per --time from --camera (or the cache's camera)."""
    width, height = relighter.description.resolution
    render_frames(
        relighter,
        args.camera or relighter.description.camera_path,
        args.time or [None],
        args.out,
        args.width or width,
        args.height or height,
        args.lights,
        args.png,
        args.fill_holes,
        layers,
    )


METHOD = BakeMethod(
    relight=RELIGHT,
    settings=MultiviewBakeSettings,
    add_options=add_options,
    settings_from_args=settings_from_args,
    bake=_bake,
    adapter=ADAPTER,
    # More caching cameras (a lower uncovered fraction), then larger caching images.
    ladder=tuple(
        {"coverage": c, "maxResolution": r}
        for c, r in (("0.1", 256), ("0.05", 256), ("0.05", 512), ("0.02", 512), ("0.02", 1024))
    ),
    stability_point={"coverage": "0.1", "maxResolution": 128, "samples": 4000},
    report=coverage_summary,
    render_views=render_views,
)
