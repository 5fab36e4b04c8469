"""The 'gather' method's bake-side registry entry (`pipeline.bake.methods`)."""

from __future__ import annotations

import argparse

from pipeline.bake.gather.adapter import ADAPTER
from pipeline.bake.gather.bake import GatherSettings, bake_gather
from pipeline.bake.methods import BakeMethod, checked
from pipeline.scene.types import Camera, Scene
from relight_torch.gather.method import METHOD as RELIGHT


def add_options(parser: argparse.ArgumentParser) -> None:
    """The `relight bake` options of the gather method."""
    gather = parser.add_argument_group("gather (--method gather)")
    gather_defaults = GatherSettings()
    gather.add_argument(
        "--directions",
        type=int,
        default=gather_defaults.num_directions,
        metavar="N",
        help=f"QMC hemisphere directions per view representative (default {gather_defaults.num_directions})",
    )
    gather.add_argument(
        "--clusters",
        type=int,
        default=gather_defaults.num_clusters,
        metavar="K",
        help=f"clustered gathers per view representative (default {gather_defaults.num_clusters})",
    )
    gather.add_argument(
        "--representatives",
        type=int,
        default=None,
        metavar="R",
        help="view representatives (default: 40,000 at 400x400, scaled with the pixel count)",
    )
    gather.add_argument(
        "--point-cells",
        type=int,
        default=gather_defaults.point_cells,
        metavar="C",
        help="cells across the scene diagonal of the grid the clustered gathers share lit surface "
        f"points on; 0 shares identical points only (default {gather_defaults.point_cells})",
    )


def settings_from_args(args: argparse.Namespace, scene: Scene, camera: Camera) -> GatherSettings:
    """The gather settings the options ask for, checked."""
    settings = GatherSettings(
        num_directions=args.directions,
        num_clusters=args.clusters,
        num_representatives=args.representatives,
        point_cells=args.point_cells,
    )
    checked("gather", settings.check)
    return settings


METHOD = BakeMethod(
    relight=RELIGHT,
    settings=GatherSettings,
    add_options=add_options,
    settings_from_args=settings_from_args,
    bake=bake_gather,  # its positional order is the registry's `Bake`
    adapter=ADAPTER,
    ladder=tuple(
        {"clusters": c, "representativeScale": f}
        for c, f in ((8, "0.25"), (16, "0.25"), (16, "0.5"), (32, "0.5"), (32, "1"), (64, "1"), (120, "1"))
    ),
    stability_point={"directions": 256, "clusters": 16, "representativeScale": "0.25"},
    # As transfer's: every edit costs S^2 and the error is mostly indirect light.
    default_supersampling=1,
)
