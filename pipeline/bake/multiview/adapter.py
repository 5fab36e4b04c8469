"""Bench adapter of the multiview method (Kim, Kyung & Lee 2009): coverage threshold x caching resolution.

The bench renders at the shot camera, so the relighter measured is the multiview cache seen from
the camera it was baked with: the correspondence map against the caching cameras, not the shot
camera's own deep framebuffer (the cache has none). Moving the camera is measured by
`pipeline.benchmarks.multiview_path`.
"""

from __future__ import annotations

from pathlib import Path

import torch

from pipeline.bake.adapter import Variant, cache_bytes
from pipeline.bake.multiview.bake import bake_multiview
from pipeline.bake.multiview.frames import FrameRenderer, read_view_camera
from pipeline.bake.multiview.placement import PlacementSettings
from pipeline.scene.types import Camera, Scene
from relight_torch.multiview.relighter import open_multiview_relighter


class MultiviewAdapter:
    """Bakes caching cameras to each coverage threshold and largest caching image side (from
    `samples` surface samples: fewer for the quick grid)."""

    name = "multiview"
    chart_axes = ("coverage", "maxResolution")

    def grid(self, quick: bool) -> list[dict[str, object]]:
        if quick:
            return [{"coverage": "0.1", "maxResolution": 128, "samples": 4000}]
        return [
            {"coverage": coverage, "maxResolution": resolution, "samples": PlacementSettings().num_samples}
            for coverage in ("0.1", "0.05", "0.02")
            for resolution in (256, 512)
        ]

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
        resolution = int(point["maxResolution"])
        settings = PlacementSettings(
            coverage=float(point["coverage"]),
            max_resolution=resolution,
            min_resolution=min(PlacementSettings().min_resolution, resolution),
            num_samples=int(point.get("samples", PlacementSettings().num_samples)),
        )
        return bake_multiview(scene, camera, directory, stem, supersampling, texture_samples, time_code, settings)

    def variants(self, layer: Path, point: dict[str, object], device: str) -> list[Variant]:
        relighter = open_multiview_relighter(layer, device=device)
        description = relighter.description
        width, height = description.resolution
        camera = read_view_camera(
            description.source, None, description.camera_path, description.parameters.get("time"), width, height
        )
        FrameRenderer(relighter).render(camera)
        return [Variant(dict(point), relighter, cache_bytes(layer))]

    def relight_view(self, variant: Variant, camera: Camera) -> torch.Tensor:
        """(H, W, 3) image of `camera` (at the cache's resolution) from the caching views; holes stay black."""
        return torch.from_numpy(FrameRenderer(variant.relighter).render(camera).image)


ADAPTER = MultiviewAdapter()
