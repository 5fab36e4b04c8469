"""The bake-side method registry: each method's relight entry extended with how it is baked.

`relight_torch.methods` names the methods and opens their caches; here each method `m` declares,
once, in `pipeline/bake/m/method.py` (`METHOD`, a `BakeMethod`), everything the pipeline needs:
its `relight bake` option group and the settings built from it, its bake, its quality ladder, its
bench adapter, its stability-suite point and its default supersampling. The bake command, the
quality sizing, the bench, the stability suite and `relight render` read these entries and keep
no list of methods of their own.
"""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from pipeline.bake.adapter import MethodAdapter
from pipeline.errors import RelightError
from pipeline.scene.types import Camera, Scene
from relight_torch.methods import METHOD_NAMES, RelightMethod, relight_method
from relight_torch.protocol import CacheRelighter

Bake = Callable[[Scene, Camera, Path, str, int, int, "float | None", object], Path]
"""(scene, camera, out_dir, stem, supersampling, texture_samples, time_code, settings) -> the cache
layer's path; `settings` as the method's `settings_from_args` built them."""


@dataclass(frozen=True)
class BakeMethod:
    """One method, as the pipeline knows it.

    Attributes:
        relight: the relight-side entry (name, opener, capabilities).
        settings: the bake settings dataclass (None: the method has no options of its own).
        add_options: adds the method's argument group to the `relight bake` parser.
        settings_from_args: (parsed `relight bake` arguments, scene, camera) -> the method's
            settings, checked; raises RelightError naming the option.
        bake: the `Bake` of the method.
        adapter: its bench adapter (`pipeline.bake.adapter.MethodAdapter`).
        ladder: the bake points `relight bake --quality` tries, cheapest first (tuples: variants
            of one bake), see `pipeline.bake.quality`.
        stability_point: its small bake point in the stability suite.
        default_supersampling: `--supersampling` when not given.
        quality_fixed: the bake-point entries `--quality` keeps as the arguments give them.
        report: a line printed after a bake (None: nothing more than the cache's summary).
        render_views: `relight render` of a cache whose relighter `needs_view`: (relighter, the
            render command's arguments, the light-group layer function or None) -> None; it
            writes the frames. Given exactly when `relight.needs_view`.
    """

    relight: RelightMethod
    settings: type | None
    add_options: Callable[[argparse.ArgumentParser], None]
    settings_from_args: Callable[[argparse.Namespace, Scene, Camera], object]
    bake: Bake
    adapter: MethodAdapter
    ladder: tuple[dict[str, object], ...]
    stability_point: dict[str, object]
    default_supersampling: int = 2
    quality_fixed: Callable[[argparse.Namespace], dict[str, object]] | None = None
    report: Callable[[Path], str] | None = None
    render_views: Callable[[CacheRelighter, argparse.Namespace, Callable | None], None] | None = None

    def __post_init__(self) -> None:
        if (self.render_views is not None) != self.relight.needs_view:
            raise ValueError(
                f"method {self.name!r}: render_views must be given exactly when its relighter needs a view"
            )
        if self.adapter.name != self.name:
            raise ValueError(f"method {self.name!r}: its adapter is named {self.adapter.name!r}")

    @property
    def name(self) -> str:
        return self.relight.name


def bake_method(name: str) -> BakeMethod:
    """The registered method `name` (`pipeline.bake.<name>.method.METHOD`).

    Raises:
        RelightError: no method of that name in this build.
    """
    relight = relight_method(name)
    method = importlib.import_module(f"pipeline.bake.{name}.method").METHOD
    if method.relight is not relight:
        raise RuntimeError(f"pipeline.bake.{name}.method does not extend relight_torch.{name}.method.METHOD")
    return method


def bake_methods() -> dict[str, BakeMethod]:
    """name -> BakeMethod of every method, in `relight_torch.methods.METHOD_NAMES` order."""
    return {name: bake_method(name) for name in METHOD_NAMES}


def checked(method: str, *checks: Callable[[], object]) -> None:
    """Run a method's settings checks; a ValueError becomes one `bake --method` error line."""
    try:
        for check in checks:
            check()
    except ValueError as error:
        raise RelightError(f"bake --method {method}: {error}") from None


def no_options(parser: argparse.ArgumentParser) -> None:
    """`add_options` of a method without options of its own."""


def no_settings(args: argparse.Namespace, scene: Scene, camera: Camera) -> None:
    """`settings_from_args` of a method without settings of its own."""
    return None
