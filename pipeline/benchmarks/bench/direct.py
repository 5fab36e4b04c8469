"""Bench adapter of the direct method: supersampling x shadow technique (no indirect light)."""

from __future__ import annotations

from pathlib import Path

from pipeline.bake.direct import bake_direct
from pipeline.benchmarks.bench.measure import cache_bytes
from pipeline.benchmarks.bench.methods import Variant
from pipeline.scene.types import Camera, Scene
from relight_torch.relighter import open_relighter


class DirectAdapter:
    """Bakes the deep framebuffer at each supersampling, relights with Embree rays or shadow maps.

    A point's 'supersampling' replaces the bench's (the one axis this method has).
    """

    name = "direct"
    chart_axes = ("supersampling", "shadows")

    def grid(self, quick: bool) -> list[dict[str, object]]:
        if quick:
            return [{"supersampling": 1, "shadows": "embree"}]
        return [{"supersampling": s, "shadows": shadows} for s in (1, 2, 3) for shadows in ("embree", "shadowmaps")]

    def bounces(self, point: dict[str, object]) -> int:
        return 0

    def bake(self, scene: Scene, camera: Camera, directory: Path, stem: str, point: dict[str, object],
             supersampling: int, texture_samples: int, time_code: float | None = None) -> Path:
        return bake_direct(scene, camera, directory, stem, int(point.get("supersampling", supersampling)),
                           texture_samples, time_code)

    def variants(self, layer: Path, point: dict[str, object], device: str) -> list[Variant]:
        relighter = open_relighter(layer, device=device, shadows=str(point.get("shadows", "embree")))
        return [Variant(dict(point), relighter, cache_bytes(layer))]


ADAPTER = DirectAdapter()
