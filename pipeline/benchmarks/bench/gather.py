"""Bench adapter of the gather method: clusters x representatives (one bounce of indirect light)."""

from __future__ import annotations

from pathlib import Path

from pipeline.bake.gather.bake import GatherSettings, bake_gather
from pipeline.benchmarks.bench.measure import cache_bytes
from pipeline.benchmarks.bench.methods import Variant
from pipeline.scene.types import Camera, Scene
from relight_torch.gather.open import open_gather_relighter


def settings(point: dict[str, object]) -> GatherSettings:
    """The bake settings of a point (keys directions, clusters, representatives; 0 = the default count)."""
    defaults = GatherSettings()
    return GatherSettings(num_directions=int(point.get("directions", defaults.num_directions)),
                          num_clusters=int(point.get("clusters", defaults.num_clusters)),
                          num_representatives=int(point.get("representatives", 0)) or None)


class GatherAdapter:
    """Clustered gathers at view representatives, radial-basis reconstruction per pixel."""

    name = "gather"
    chart_axes = ("clusters", "representatives")

    def grid(self, quick: bool) -> list[dict[str, object]]:
        if quick:
            return [{"directions": 256, "clusters": 16, "representatives": 64}]
        return [{"directions": 2048, "clusters": clusters, "representatives": representatives}
                for representatives in (0, 4000) for clusters in (30, 60, 120)]

    def bounces(self, point: dict[str, object]) -> int:
        return 1

    def bake(self, scene: Scene, camera: Camera, directory: Path, stem: str, point: dict[str, object],
             supersampling: int, texture_samples: int, time_code: float | None = None) -> Path:
        return bake_gather(scene, camera, directory, stem, supersampling, texture_samples, time_code=time_code,
                           settings=settings(point), progress=False)

    def variants(self, layer: Path, point: dict[str, object], device: str) -> list[Variant]:
        return [Variant(settings(point).parameters(), open_gather_relighter(layer, device=device), cache_bytes(layer))]


ADAPTER = GatherAdapter()
