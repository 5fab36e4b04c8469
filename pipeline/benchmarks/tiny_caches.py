"""Tiny caches of every method (the bundled Cornell box at 16 x 12, small settings, about a second
each): what the fault, fuzz and long-session measurements work on."""

from __future__ import annotations

import contextlib
import io
import logging
from pathlib import Path

from pipeline import cli
from pipeline.errors import RelightError
from pipeline.scenes import SCENES

SCENE = "cornell_box"
WIDTH, HEIGHT = 16, 12
COMMON_OPTIONS = ["--width", str(WIDTH), "--height", str(HEIGHT), "--supersampling", "1", "--texture-samples", "1"]
METHOD_OPTIONS = {
    "direct": [],
    "transfer": ["--gathers", "16", "--coefficients", "8", "--bounces", "2", "--bounce-coefficients", "4"],
    "gather": ["--directions", "16", "--clusters", "4", "--representatives", "32"],
    "cuts": ["--mode", "indirect", "--cut-lights", "16"],
    "multiview": ["--caching-resolution", "16", "--coverage", "0.5"],
}
METHODS = tuple(METHOD_OPTIONS)


def bake_arguments(shot: Path, out: Path, method: str) -> list[str]:
    """`relight bake` arguments of the tiny bake of `method`."""
    return [
        "bake",
        str(shot),
        "--camera",
        SCENES[SCENE].camera,
        "--out",
        str(out),
        "--method",
        method,
        *COMMON_OPTIONS,
        *METHOD_OPTIONS[method],
    ]


def quiet_main(arguments: list[str]) -> tuple[int, str]:
    """`relight ARGUMENTS` in this process -> (exit status, stderr with its log lines); stdout is discarded.

    The log lines get a handler of their own: `cli.main`'s `logging.basicConfig` acts only when
    the root logger has none, so it binds the first call's stderr (or none, under pytest's own
    handlers).
    """
    stderr = io.StringIO()
    handler = logging.StreamHandler(stderr)
    handler.setFormatter(logging.Formatter(cli.LOG_FORMAT))
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        with contextlib.redirect_stderr(stderr), contextlib.redirect_stdout(io.StringIO()):
            status = cli.main(arguments)
    finally:
        root.removeHandler(handler)
    return status, stderr.getvalue()


def bake_tiny(directory: Path, methods: tuple[str, ...] = METHODS) -> dict[str, Path]:
    """The shot under directory/scene and one tiny cache per method under directory/<method>.

    Returns:
        method -> cache layer.

    Raises:
        RelightError: a bake failed (its message).
    """
    shot = SCENES[SCENE].write(directory / "scene")
    layers = {}
    for method in methods:
        status, stderr = quiet_main(bake_arguments(shot, directory / method, method))
        if status != 0:
            raise RelightError(f"tiny {method} bake failed: {stderr.strip()}")
        layers[method] = directory / method / f"{SCENE}.relight.usda"
    return layers
