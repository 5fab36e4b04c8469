"""Bench adapter of the direct method: supersampling x shadow technique x light samples x shadow
filter (no indirect light).

Light samples per shading point of an area light (`RelightSettings.area_samples`) and the radius of
the ratio estimator's visibility filter (`RelightSettings.shadow_filter_radius`) are relight
settings: every pair of a point's 'areaSamples' and 'shadowFilter' tuples is relit from one bake.
"""

from __future__ import annotations

from pathlib import Path

from pipeline.bake.adapter import Variant, cache_bytes
from pipeline.bake.direct.bake import bake_direct
from pipeline.scene.types import Camera, Scene
from relight_torch.direct.relighter import open_relighter
from relight_torch.direct.settings import RelightSettings


def setting_values(point: dict[str, object], key: str, default: int) -> list[int]:
    """The point's values of a relight setting (an int or a tuple; `default` when absent)."""
    value = point.get(key, default)
    return sorted(value) if isinstance(value, tuple) else [int(value)]


class DirectAdapter:
    """Bakes the deep framebuffer at each supersampling, relights with Embree rays or shadow maps.

    A point's 'supersampling' replaces the bench's (the one axis this method has).
    """

    name = "direct"
    chart_axes = ("areaSamples", "supersampling")

    def grid(self, quick: bool) -> list[dict[str, object]]:
        # Rect and sphere lights take the ratio estimator (lights/ratio.py): a few samples are accurate,
        # and with their visibility filtered one sample can do.
        if quick:
            return [{"supersampling": 1, "shadows": "embree", "areaSamples": (1, 2, 4, 16), "shadowFilter": (0, 2, 4)}]
        # Shadow maps render one map per light sample (a GPU technique: seconds per frame on a CPU).
        return [
            {"supersampling": s, "shadows": "embree", "areaSamples": (1, 2, 4, 16), "shadowFilter": (0, 2)}
            for s in (1, 2)
        ] + [{"supersampling": 1, "shadows": "shadowmaps", "areaSamples": (1, 4)}]

    def bounces(self, point: dict[str, object]) -> int:
        return 0

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
        return bake_direct(
            scene, camera, directory, stem, int(point.get("supersampling", supersampling)), texture_samples, time_code
        )

    def variants(self, layer: Path, point: dict[str, object], device: str) -> list[Variant]:
        shadows = str(point.get("shadows", "embree"))
        defaults = RelightSettings()
        return [
            Variant(
                {**point, "areaSamples": count, "shadowFilter": radius},
                open_relighter(
                    layer,
                    device=device,
                    shadows=shadows,
                    settings=RelightSettings(
                        area_samples=count, filtered_area_samples=count, shadow_filter_radius=radius
                    ),
                ),
                cache_bytes(layer),
            )
            for count in setting_values(point, "areaSamples", defaults.area_samples)
            for radius in setting_values(point, "shadowFilter", 0)
        ]


ADAPTER = DirectAdapter()
