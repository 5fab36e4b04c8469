"""Bench adapter of the direct method: supersampling x shadow technique x light samples (no indirect light).

Light samples per shading point of an area light (`RelightSettings.area_samples`) are a relight
setting: every count of a point's 'areaSamples' tuple is relit from one bake.
"""

from __future__ import annotations

from pathlib import Path

from pipeline.bake.direct import bake_direct
from pipeline.benchmarks.bench.measure import cache_bytes
from pipeline.benchmarks.bench.methods import Variant
from pipeline.scene.types import Camera, Scene
from relight_torch.relighter import RelightSettings, open_relighter


def sample_counts(point: dict[str, object]) -> list[int]:
    """The point's area-light sample counts (an int or a tuple; default the relighter's)."""
    value = point.get("areaSamples", RelightSettings().area_samples)
    return sorted(value) if isinstance(value, tuple) else [int(value)]


class DirectAdapter:
    """Bakes the deep framebuffer at each supersampling, relights with Embree rays or shadow maps.

    A point's 'supersampling' replaces the bench's (the one axis this method has).
    """

    name = "direct"
    chart_axes = ("areaSamples", "supersampling")

    def grid(self, quick: bool) -> list[dict[str, object]]:
        if quick:
            return [{"supersampling": 1, "shadows": "embree", "areaSamples": (4, 16)}]
        # Shadow maps render one map per light sample (a GPU technique: seconds per frame on a CPU).
        return [{"supersampling": s, "shadows": "embree", "areaSamples": (1, 4, 16)} for s in (1, 2)] + [
            {"supersampling": 1, "shadows": "shadowmaps", "areaSamples": (1, 4)}]

    def bounces(self, point: dict[str, object]) -> int:
        return 0

    def bake(self, scene: Scene, camera: Camera, directory: Path, stem: str, point: dict[str, object],
             supersampling: int, texture_samples: int, time_code: float | None = None) -> Path:
        return bake_direct(scene, camera, directory, stem, int(point.get("supersampling", supersampling)),
                           texture_samples, time_code)

    def variants(self, layer: Path, point: dict[str, object], device: str) -> list[Variant]:
        shadows = str(point.get("shadows", "embree"))
        return [Variant({**point, "areaSamples": count},
                        open_relighter(layer, device=device, shadows=shadows,
                                       settings=RelightSettings(area_samples=count)), cache_bytes(layer))
                for count in sample_counts(point)]


ADAPTER = DirectAdapter()
