"""The adapter protocol `relight bench` runs every method through, and the registry of methods.

An adapter is a module of this package exposing `ADAPTER`, an object with

    name: str                                   the `method` column ('direct', 'transfer', ...)
    chart_axes: tuple[str, str | None]          the params key its parameter chart puts on x
                                                and the one that makes one curve per value
    grid(quick: bool) -> list[dict[str, object]]
        the bake configurations to sweep: one or two small ones for `--quick` (seconds at the
        quick size), the full sweep otherwise. Values are ints or strings without spaces, or a
        tuple for an axis studied from one bake (transfer's kept coefficients).
    bounces(point) -> int
        indirect bounces the method computes at `point` (its reference's max_bounces; 0: direct only).
    bake(scene: Scene, camera: Camera, directory: Path, stem: str, point,
         supersampling: int, texture_samples: int, time_code: float | None = None) -> Path
        bake `point` into `directory` (made by the caller, one per point); the cache layer's path.
        `time_code` is the time the scene was read at (recorded in the cache, as the bakers do).
    variants(layer: Path, point, device: str) -> list[Variant]
        the relighters to measure from that cache: one per parameter variant (a tuple axis of
        `point` gives several), each with its parameters (the `params` column) and the bytes its
        cache takes.

`measure.run_point` bakes one point for a `BenchScene` and measures every variant under every light
edit (`measure.relit_rows`); the stability suite and the quality sizing call `bake` and
`variants` directly on their own scenes and lights. Adapters never render references.

Adding a method (cuts, multiview): write `pipeline/bake/<method>/adapter.py` with `ADAPTER`
and add its module name to METHOD_MODULES below. The bench, its chart and its tests pick it up.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple, Protocol

from pipeline.benchmarks.bench.references import References
from pipeline.scene import find_camera, load_scene
from pipeline.scene.types import Camera, Scene

METHOD_MODULES = ("direct", "transfer", "gather", "cuts", "multiview")
"""Modules of this package holding an `ADAPTER`, in the order the bench runs them."""


@dataclass(frozen=True)
class BenchScene:
    """What the runner prepares once per bundled scene and hands every adapter.

    Attributes:
        name: bundled scene name (`pipeline.scenes.SCENES`).
        shot: the written USD stage.
        camera: prim path of the camera to bake and render.
        width, height: image size in pixels.
        edits: light edit name -> lights layer ('shot' -> None: the stage's own lights).
        directory: where this scene's caches go (an adapter makes its own subdirectory).
        device: torch device the relighters run on ('cpu', 'cuda').
        repeats: timed light edits per relight_ms median.
        references: the reference images, rendered on first use and cached.
        supersampling, texture_samples: of every method's direct part (not swept, so that the
            methods differ in what they add; the direct adapter sweeps supersampling).
    """

    name: str
    shot: Path
    camera: str
    width: int
    height: int
    edits: dict[str, Path | None]
    directory: Path
    device: str
    repeats: int
    references: References
    supersampling: int = 2
    texture_samples: int = 2

    def load(self) -> tuple[Scene, Camera]:
        """The stage at the bench size, under its own lights, and the camera."""
        scene = load_scene(self.shot, width=self.width, height=self.height)
        return scene, find_camera(scene, self.camera)

    def cache_dir(self, method: str, point: dict[str, object]) -> Path:
        """`directory / '<method>-<key>-<value>-...'`: one cache directory per bake configuration."""
        parts = [method] + [f"{key}-{'_'.join(map(str, value)) if isinstance(value, tuple) else value}"
                            for key, value in point.items()]
        return self.directory / "-".join(parts)


class Variant(NamedTuple):
    """One relighter to measure: its parameters (the params column), itself, its cache's bytes."""

    parameters: dict[str, object]
    relighter: Any
    cache_bytes: float


class MethodAdapter(Protocol):
    """See the module docstring."""

    name: str
    chart_axes: tuple[str, str | None]

    def grid(self, quick: bool) -> list[dict[str, object]]: ...

    def bounces(self, point: dict[str, object]) -> int: ...

    def bake(self, scene: Scene, camera: Camera, directory: Path, stem: str, point: dict[str, object],
             supersampling: int, texture_samples: int, time_code: float | None = None) -> Path: ...

    def variants(self, layer: Path, point: dict[str, object], device: str) -> list[Variant]: ...


def adapters(names: list[str] | tuple[str, ...] | None = None) -> dict[str, MethodAdapter]:
    """name -> ADAPTER of the registered methods (all of them, or those named, in registry order).

    Raises:
        ValueError: a name is not registered.
    """
    registered = {name: importlib.import_module(f"pipeline.bake.{name}.adapter").ADAPTER
                  for name in METHOD_MODULES}
    unknown = sorted(set(names or ()) - set(registered))
    if unknown:
        raise ValueError(f"unknown method(s) {unknown}; registered: {list(registered)}")
    return {name: adapter for name, adapter in registered.items() if names is None or name in names}
