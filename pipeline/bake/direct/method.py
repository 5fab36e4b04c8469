"""The 'direct' method's bake-side registry entry (`pipeline.bake.methods`)."""

from __future__ import annotations

from pathlib import Path

from pipeline.bake.direct.adapter import ADAPTER
from pipeline.bake.direct.bake import bake_direct
from pipeline.bake.methods import BakeMethod, no_options, no_settings
from pipeline.scene.types import Camera, Scene
from relight_torch.direct.method import METHOD as RELIGHT


def _bake(
    scene: Scene,
    camera: Camera,
    out_dir: Path,
    stem: str,
    supersampling: int,
    texture_samples: int,
    time_code: float | None,
    settings: None,
) -> Path:
    return bake_direct(scene, camera, out_dir, stem, supersampling, texture_samples, time_code=time_code)


METHOD = BakeMethod(
    relight=RELIGHT,
    settings=None,
    add_options=no_options,
    settings_from_args=no_settings,
    bake=_bake,
    adapter=ADAPTER,
    ladder=tuple({"supersampling": s} for s in (1, 2, 3, 4)),
    stability_point={"supersampling": 1, "shadows": "embree"},
)
