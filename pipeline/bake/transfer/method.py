"""The 'transfer' method's bake-side registry entry (`pipeline.bake.methods`)."""

from __future__ import annotations

import argparse

from pipeline.bake.methods import BakeMethod, checked
from pipeline.bake.transfer.adapter import ADAPTER
from pipeline.bake.transfer.bake import TransferSettings, bake_transfer, reduced_view
from pipeline.scene.types import Camera, Scene
from relight_torch.transfer.method import METHOD as RELIGHT


def add_options(parser: argparse.ArgumentParser) -> None:
    """The `relight bake` options of the transfer method."""
    transfer = parser.add_argument_group("transfer (--method transfer)")
    defaults = TransferSettings()
    transfer.add_argument(
        "--gathers",
        type=int,
        default=defaults.num_gathers,
        metavar="G",
        help=f"gather samples, a power of 4 (default {defaults.num_gathers})",
    )
    transfer.add_argument(
        "--coefficients",
        type=int,
        default=defaults.num_coefficients,
        metavar="K",
        help=f"wavelet coefficients kept per final-gather row (default {defaults.num_coefficients})",
    )
    transfer.add_argument(
        "--bounces",
        type=int,
        default=defaults.num_bounces,
        metavar="B",
        help="indirect bounces; 1 bakes the final gather only (default 1)",
    )
    transfer.add_argument(
        "--bounce-coefficients",
        type=int,
        default=defaults.num_bounce_coefficients,
        metavar="K",
        help=f"coefficients kept per gather-to-gather row (default {defaults.num_bounce_coefficients})",
    )
    transfer.add_argument(
        "--quantize",
        action="store_true",
        help="store coefficients as 8 bits with a per-row scale and offset (default float16)",
    )
    transfer.add_argument(
        "--indirect-scale",
        type=int,
        default=defaults.indirect_scale,
        metavar="S",
        help="bake the final gather for an image S times smaller per side, upsampled edge-aware "
        "at relight time (S must divide the width and height; default 2 from 240 pixels on "
        "the shorter side, else 1)",
    )


def settings_from_args(args: argparse.Namespace, scene: Scene, camera: Camera) -> TransferSettings:
    """The transfer settings the options ask for, checked against the camera's image."""
    settings = TransferSettings(
        num_gathers=args.gathers,
        num_coefficients=args.coefficients,
        num_bounces=args.bounces,
        num_bounce_coefficients=args.bounce_coefficients,
        encoding="uint8" if args.quantize else "float16",
        indirect_scale=args.indirect_scale,
    )
    checked("transfer", settings.check, lambda: reduced_view(scene, camera, settings.for_view(camera).indirect_scale))
    return settings


METHOD = BakeMethod(
    relight=RELIGHT,
    settings=TransferSettings,
    add_options=add_options,
    settings_from_args=settings_from_args,
    bake=bake_transfer,  # its positional order is the registry's `Bake`
    adapter=ADAPTER,
    ladder=tuple({"gathers": g, "coefficients": (10, 25, 50, 100, 200)} for g in (1024, 4096, 16384)),
    stability_point={"gathers": 1024, "coefficients": 50, "bounces": 1},
    # One sub-sample per pixel: every edit costs S^2 and the error is mostly indirect light, not
    # the edges' aliasing (docs/ACCURACY.md, 'Size-aware defaults').
    default_supersampling=1,
    quality_fixed=lambda args: {"bounces": args.bounces},
)
