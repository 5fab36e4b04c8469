"""The adapter protocol every method's bake points go through (quality sizing, `relight bench`,
the stability suite), and the bake-point helpers the adapters share.

An adapter (`pipeline/bake/<method>/adapter.py`, registered as its method's `BakeMethod.adapter`)
is an object with

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

Adapters never render references: the bench (`pipeline.benchmarks.bench.measure`), the stability
suite and the quality sizing (`pipeline.bake.quality`) do, and call `bake` and `variants`.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import NamedTuple, Protocol

from pipeline.scene.types import Camera, Scene
from relight_torch.cache.layer import read_cache_layer
from relight_torch.protocol import CacheRelighter


class Variant(NamedTuple):
    """One relighter to measure: its parameters (the params column), itself, its cache's bytes."""

    parameters: dict[str, object]
    relighter: CacheRelighter
    cache_bytes: float


class MethodAdapter(Protocol):
    """See the module docstring."""

    name: str
    chart_axes: tuple[str, str | None]

    def grid(self, quick: bool) -> list[dict[str, object]]: ...

    def bounces(self, point: dict[str, object]) -> int: ...

    def bake(
        self,
        scene: Scene,
        camera: Camera,
        directory: Path,
        stem: str,
        point: dict[str, object],
        supersampling: int,
        texture_samples: int,
        time_code: float | None = None,
    ) -> Path: ...

    def variants(self, layer: Path, point: dict[str, object], device: str) -> list[Variant]: ...


def cache_bytes(layer: Path) -> int:
    """Bytes of a cache layer's payloads."""
    return sum(payload.num_bytes for payload in read_cache_layer(layer).payloads)


def format_params(parameters: Mapping[str, object]) -> str:
    """'key=value key=value' in the mapping's order (values must not contain spaces or '=')."""
    for key, value in parameters.items():
        if any(c in f"{key}{value}" for c in " =,"):
            raise ValueError(f"parameter {key}={value!r} must not contain spaces, '=' or ','")
    return " ".join(f"{key}={value}" for key, value in parameters.items())


def parse_params(text: str) -> dict[str, str]:
    """The inverse of `format_params`."""
    return dict(item.split("=", 1) for item in text.split())
