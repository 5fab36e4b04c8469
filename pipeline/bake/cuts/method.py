"""The 'cuts' method's bake-side registry entry (`pipeline.bake.methods`)."""

from __future__ import annotations

import argparse

from pipeline.bake.cuts.adapter import ADAPTER
from pipeline.bake.cuts.bake import MODES, CutsSettings, bake_cuts
from pipeline.bake.methods import BakeMethod, checked
from pipeline.scene.types import Camera, Scene
from relight_torch.cuts.method import METHOD as RELIGHT


def add_options(parser: argparse.ArgumentParser) -> None:
    """The `relight bake` options of the cuts method."""
    cuts = parser.add_argument_group("cuts (--method cuts)")
    cuts_defaults = CutsSettings()
    cuts.add_argument(
        "--mode",
        default=cuts_defaults.mode,
        choices=MODES,
        help="light points: 'env' = directions on the sphere (dome lights), 'indirect' = surface "
        "points (one diffuse bounce of every light; --cut-lights a power of 4) (default env)",
    )
    cuts.add_argument(
        "--cut-lights",
        type=int,
        default=cuts_defaults.num_lights,
        metavar="L",
        help=f"point lights in the light tree, a power of two (default {cuts_defaults.num_lights})",
    )
    cuts.add_argument(
        "--sigma",
        type=float,
        default=cuts_defaults.sigma,
        metavar="SIGMA",
        help=f"visibility cut threshold |C| var <= SIGMA^2 (default {cuts_defaults.sigma})",
    )
    cuts.add_argument(
        "--lattice-edge",
        type=float,
        default=cuts_defaults.lattice_edge,
        metavar="F",
        help="longest edge of the refined triangles carrying visibility cuts, as a fraction of the "
        f"scene diagonal (default {cuts_defaults.lattice_edge:.4g})",
    )
    cuts.add_argument(
        "--beta",
        type=float,
        default=cuts_defaults.beta,
        metavar="B",
        help="data-driven light tree: blend of geometric and pilot-visibility distances, "
        "0.4-0.5 in the paper (default 1: geometric only)",
    )


def settings_from_args(args: argparse.Namespace, scene: Scene, camera: Camera) -> CutsSettings:
    """The cuts settings the options ask for, checked."""
    settings = CutsSettings(
        mode=args.mode, num_lights=args.cut_lights, sigma=args.sigma, lattice_edge=args.lattice_edge, beta=args.beta
    )
    checked("cuts", settings.check)
    return settings


METHOD = BakeMethod(
    relight=RELIGHT,
    settings=CutsSettings,
    add_options=add_options,
    settings_from_args=settings_from_args,
    bake=bake_cuts,  # its positional order is the registry's `Bake`
    adapter=ADAPTER,
    # A smaller sigma refines the visibility cuts (bytes); the illumination cut sizes cost relight
    # time only and come from one bake, so the cheapest passing one is kept.
    ladder=tuple(
        {"lights": n, "sigma": s, "cut": (128, 256, 512)}
        for n, s in ((1024, 3.0), (1024, 2.0), (4096, 2.0), (4096, 1.5), (16384, 1.5), (65536, 1.5))
    ),
    stability_point={"lights": 1024, "sigma": 2.0, "cut": 256},
    quality_fixed=lambda args: {"mode": args.mode},
)
