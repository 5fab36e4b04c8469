"""Options shared by several subcommands, so each means the same everywhere."""

from __future__ import annotations

import argparse

from pipeline.errors import RelightError
from relight_torch.direct.settings import MEMORY_BUDGET_FRACTION, RelightSettings


def add_camera_options(parser: argparse.ArgumentParser, required: bool = True) -> None:
    """--camera PRIM, --width W, --height H, --time T."""
    group = parser.add_argument_group("camera")
    group.add_argument(
        "--camera", required=required, metavar="PRIM", help="camera prim path in the stage, e.g. /World/Camera"
    )
    group.add_argument(
        "--width", type=int, metavar="W", help="image width in pixels (default: the stage's RenderSettings, else 640)"
    )
    group.add_argument(
        "--height", type=int, metavar="H", help="image height in pixels (default: the stage's RenderSettings, else 480)"
    )
    group.add_argument(
        "--time", type=float, default=None, metavar="T", help="USD time code to read (default: the default time)"
    )


def add_lights_option(parser: argparse.ArgumentParser) -> None:
    """--lights LAYER: a USD layer of light edits composed as the strongest sublayer."""
    parser.add_argument(
        "--lights", metavar="LAYER", help="USD layer of light edits, composed as the strongest sublayer over the shot"
    )


def add_materials_option(parser: argparse.ArgumentParser, where: str = "") -> None:
    """--materials LAYER: a USD layer of material edits (`relight_torch.material_edits`)."""
    parser.add_argument(
        "--materials",
        metavar="LAYER",
        help="USD layer of material edits: constant UsdPreviewSurface inputs (inputs:diffuseColor, "
        f"inputs:roughness, ...) authored on the shot's materials or their shaders{where}",
    )


def add_device_option(parser: argparse.ArgumentParser) -> None:
    """--device cpu|cuda."""
    parser.add_argument(
        "--device",
        default="cpu",
        choices=("cpu", "cuda"),
        help="torch device for the relighting kernels (default: cpu)",
    )


def add_memory_budget_option(parser: argparse.ArgumentParser) -> None:
    """--memory-budget GB: `RelightSettings.memory_budget` (read back by `relight_settings`)."""
    parser.add_argument(
        "--memory-budget",
        type=float,
        metavar="GB",
        help="memory the relighter's per-light caches may keep, in GB (default: "
        f"{MEMORY_BUDGET_FRACTION:.3g} of this machine's memory); less keeps fewer lights' "
        "transports and unit images in half precision",
    )


def relight_settings(args: argparse.Namespace) -> RelightSettings:
    """The relighter's settings from --memory-budget (GB).

    Raises:
        RelightError: a negative budget.
    """
    if args.memory_budget is None:
        return RelightSettings()
    if args.memory_budget < 0:
        raise RelightError(f"--memory-budget must be >= 0 GB, got {args.memory_budget}")
    return RelightSettings(memory_budget=int(args.memory_budget * 1e9))
