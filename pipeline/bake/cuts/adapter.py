"""Bench adapter of the cuts method (Cheslack-Postava et al. 2008, env mode): lights x sigma, cut sizes per bake.

Dome lights are relit by cuts, every other light by the direct relighter: on a scene without a
dome the rows measure the direct part alone (the `dome` bundled scene is the one this method is for).
"""

from __future__ import annotations

from pathlib import Path

from pipeline.bake.adapter import Variant, cache_bytes
from pipeline.bake.cuts.bake import CutsSettings, bake_cuts
from pipeline.scene.types import Camera, Scene
from relight_torch.cuts.open import open_cuts_relighter
from relight_torch.cuts.relighter import CutsRelightSettings

CUT_SIZES = (128, 256, 512)
"""Illumination cut sizes relit from every bake (Cheslack-Postava et al. 2008's three)."""


def settings(point: dict[str, object]) -> CutsSettings:
    """The bake settings of a point (keys lights, sigma, mode)."""
    defaults = CutsSettings()
    return CutsSettings(
        mode=str(point.get("mode", defaults.mode)),
        num_lights=int(point.get("lights", defaults.num_lights)),
        sigma=float(point.get("sigma", defaults.sigma)),
    )


class CutsAdapter:
    """Visibility cuts per lattice vertex, merged per sub-sample with the frame's illumination cut."""

    name = "cuts"
    chart_axes = ("cut", "sigma")

    def grid(self, quick: bool) -> list[dict[str, object]]:
        if quick:
            return [{"lights": 1024, "sigma": 2.0}]
        return [{"lights": 8192, "sigma": sigma} for sigma in (1.5, 2.0, 3.0)]

    def bounces(self, point: dict[str, object]) -> int:
        return 1 if settings(point).mode == "indirect" else 0

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
        return bake_cuts(
            scene,
            camera,
            directory,
            stem,
            supersampling,
            texture_samples,
            time_code=time_code,
            settings=settings(point),
        )

    def variants(self, layer: Path, point: dict[str, object], device: str) -> list[Variant]:
        """One variant per illumination cut size: the point's 'cut' (a size or a tuple), else CUT_SIZES."""
        num_bytes, bake = cache_bytes(layer), settings(point)
        sizes = point.get("cut", CUT_SIZES)
        sizes = tuple(int(size) for size in (sizes if isinstance(sizes, tuple) else (sizes,)))
        return [
            Variant(
                {"mode": bake.mode, "lights": bake.num_lights, "sigma": bake.sigma, "cut": size},
                open_cuts_relighter(layer, device=device, cuts_settings=CutsRelightSettings(max_cut=size)),
                num_bytes,
            )
            for size in sizes
        ]


ADAPTER = CutsAdapter()
