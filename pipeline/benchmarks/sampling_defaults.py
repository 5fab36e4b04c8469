"""Light sampling settings of the direct relighter against a many-sample relight of the same cache.

    python -m pipeline.benchmarks.sampling_defaults SCENE --width W --height H
        [--supersampling S] [--truth-samples 64] [--out DIR]

Bakes the scene's direct cache and relights it under the shot's lights with the defaults (the
visibility filter sized from the image, `relighter.auto_filter_radius`; one sample for filtered
rect lights in matte images), with the old defaults (16 samples, no filter) and with 16 filtered
samples. Prints per setting the filter radius, the PSNR against `--truth-samples` unfiltered
samples (the sampling error alone: same cache, same shadow rays) and the first render's CPU
seconds (this process's time).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

from pipeline.bake.direct.bake import bake_direct
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES
from relight_torch.direct.relighter import open_relighter
from relight_torch.direct.settings import RelightSettings
from relight_torch.metrics import psnr

SETTINGS = {
    "defaults": RelightSettings(),
    "16 unfiltered": RelightSettings(shadow_filter_radius=0),
    "16 filtered": RelightSettings(filtered_area_samples=16),
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene", choices=sorted(SCENES))
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--supersampling", type=int, default=1)
    parser.add_argument("--truth-samples", type=int, default=64)
    parser.add_argument("--out", type=Path, help="directory for the scene and cache (default: a temporary one)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as scratch:
        directory = args.out or Path(scratch)
        bundled = SCENES[args.scene]
        scene = load_scene(bundled.write(directory / "scene"), width=args.width, height=args.height)
        layer = bake_direct(
            scene, find_camera(scene, bundled.camera), directory / "cache", args.scene, args.supersampling, 1
        )
        truth = open_relighter(
            layer, settings=RelightSettings(shadow_filter_radius=0, area_samples=args.truth_samples)
        ).render()
        print("setting,filter_radius,psnr_db,first_render_cpu_s")
        for name, settings in SETTINGS.items():
            relighter = open_relighter(layer, settings=settings)
            start = time.process_time()
            image = relighter.render()
            seconds = time.process_time() - start
            print(
                f"{name},{relighter.filter_radius},{psnr(image.numpy(), truth.numpy()):.2f},{seconds:.2f}", flush=True
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
