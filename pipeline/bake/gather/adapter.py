"""Bench adapter of the gather method: clusters x representatives (one bounce of indirect light)."""

from __future__ import annotations

from pathlib import Path

from pipeline.bake.adapter import Variant, cache_bytes
from pipeline.bake.gather.bake import GatherSettings, bake_gather
from pipeline.scene.types import Camera, Scene
from relight_torch.cache.layer import read_cache_layer
from relight_torch.gather.open import open_gather_relighter


def settings(point: dict[str, object], num_pixels: int) -> GatherSettings:
    """The bake settings of a point at an image of `num_pixels`.

    Keys: directions, clusters, representativeScale (the view representatives as a multiple of the
    default count at that size, so that one grid means the same density at every bench size).
    """
    defaults = GatherSettings()
    scale = float(point.get("representativeScale", 1.0))
    return GatherSettings(
        num_directions=int(point.get("directions", defaults.num_directions)),
        num_clusters=int(point.get("clusters", defaults.num_clusters)),
        num_representatives=None if scale == 1.0 else max(1, round(scale * defaults.representatives(num_pixels))),
    )


class GatherAdapter:
    """Clustered gathers at view representatives, radial-basis reconstruction per pixel."""

    name = "gather"
    chart_axes = ("clusters", "representativeScale")

    def grid(self, quick: bool) -> list[dict[str, object]]:
        if quick:
            return [{"directions": 256, "clusters": 16, "representativeScale": "0.5"}]
        return [
            {"directions": 2048, "clusters": clusters, "representativeScale": scale}
            for scale in ("0.25", "1")
            for clusters in (30, 60, 120)
        ]

    def bounces(self, point: dict[str, object]) -> int:
        return 1

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
    ) -> Path:
        return bake_gather(
            scene,
            camera,
            directory,
            stem,
            supersampling,
            texture_samples,
            time_code=time_code,
            settings=settings(point, camera.width * camera.height),
            progress=False,
        )

    def variants(self, layer: Path, point: dict[str, object], device: str) -> list[Variant]:
        width, height = read_cache_layer(layer).resolution
        parameters = {
            **settings(point, width * height).parameters(),
            "representativeScale": point.get("representativeScale", "1"),
        }
        return [Variant(parameters, open_gather_relighter(layer, device=device), cache_bytes(layer))]


ADAPTER = GatherAdapter()
