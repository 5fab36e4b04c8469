"""The relight-side method registry: each relighting method declared once, by name.

`METHOD_NAMES` is the one list of methods in the project. Each name `m` has a package
`relight_torch.m` whose module `relight_torch.m.method` holds `METHOD`, a `RelightMethod`: the
opener of an 'm' cache and what the method needs. The bake side (`pipeline.bake.methods`) extends
each entry with the method's bake, CLI options, quality ladder and bench adapter; nothing else
keeps a list of methods or branches on a method's name. Entries are imported on first use, so
importing this module imports no method.

Adding a method: a package `relight_torch/<name>/` with `method.py` declaring `METHOD`, its bake
side `pipeline/bake/<name>/method.py` declaring `pipeline.bake.methods.BakeMethod`, and its name
below.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from relight_torch.errors import RelightError

if TYPE_CHECKING:  # types only: the direct method's package is imported by its entry, not here
    from relight_torch.direct.settings import RelightSettings
    from relight_torch.protocol import CacheRelighter

METHOD_NAMES = ("direct", "transfer", "gather", "cuts", "multiview")
"""Every relighting method of this build, in the order the bench runs them."""

Opener = Callable[
    [str | os.PathLike[str], str | torch.device, str, str | os.PathLike[str] | None, "RelightSettings"],
    "CacheRelighter",
]
"""(cache layer path, device, shadows ('embree' or 'shadowmaps'), lights layer or None, direct
relight settings) -> the cache's relighter, with the shot's lights; raises RelightError."""


@dataclass(frozen=True)
class RelightMethod:
    """One relighting method, as `relight_torch` knows it.

    Attributes:
        name: the cache layer's `relight:method` ('direct', 'transfer', ...).
        open: the `Opener` of a cache of this method.
        builds_on: the other methods whose packages this one's modules import (every method but
            'direct' composes the direct relighter, which owns the lights and the direct light).
            Nothing else: siblings share through neutral modules below them.
        needs_view: the relighter renders nothing until it is given a view (`set_view`): the
            method relights cameras other than the baked one (`relight render --camera`).
    """

    name: str
    open: Opener
    builds_on: tuple[str, ...] = ()
    needs_view: bool = False


def relight_method(name: str) -> RelightMethod:
    """The registered method `name`.

    Raises:
        RelightError: no method of that name in this build.
    """
    if name not in METHOD_NAMES:
        raise RelightError(f"no relighting method {name!r} in this build (it has {', '.join(METHOD_NAMES)})")
    method = importlib.import_module(f"relight_torch.{name}.method").METHOD
    if method.name != name:
        raise RuntimeError(f"relight_torch.{name}.method declares {method.name!r}, not {name!r}")
    return method


def relight_methods() -> dict[str, RelightMethod]:
    """name -> RelightMethod of every method, in `METHOD_NAMES` order."""
    return {name: relight_method(name) for name in METHOD_NAMES}
