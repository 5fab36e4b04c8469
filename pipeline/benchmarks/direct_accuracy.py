"""Accuracy of direct relighting against the reference, per light edit, for the notes and docs.

    python -m pipeline.benchmarks.direct_accuracy SCENE --width W --height H --spp N
        [--supersampling S] [--texture-samples T] [--shadows embree [shadowmaps]] [--out DIR]

Bakes the bundled scene, relights it under the shot's lights and every example light edit, renders
the reference (max-bounces 0, same lights layer) and prints PSNR, relMSE and the reference's own
noise floor (the PSNR its variance alone would allow), as one CSV row per edit and shadow
technique (each edit's reference is rendered once for all of them).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from pipeline.bake.direct.bake import bake_direct
from pipeline.reference.path_tracer import PathTracer, ReferenceSettings
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES, light_edit_layers
from relight_torch.direct.loading import shot_lights
from relight_torch.direct.relighter import open_relighter
from relight_torch.metrics import psnr, rel_mse


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene", choices=sorted(SCENES))
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--spp", type=int, default=256, help="reference samples per pixel")
    parser.add_argument("--supersampling", type=int, default=2)
    parser.add_argument("--texture-samples", type=int, default=2)
    parser.add_argument("--shadows", nargs="+", default=["embree"], choices=("embree", "shadowmaps"))
    parser.add_argument("--out", help="directory for the scene and cache (default: a temporary one)")
    args = parser.parse_args(argv)
    directory = Path(args.out or tempfile.mkdtemp(prefix="relight-accuracy-"))
    bundled = SCENES[args.scene]
    shot = bundled.write(directory)
    edits = light_edit_layers(args.scene, directory)
    scene = load_scene(shot, width=args.width, height=args.height)
    cache = bake_direct(
        scene,
        find_camera(scene, bundled.camera),
        directory / "cache",
        args.scene,
        args.supersampling,
        args.texture_samples,
    )
    relighters = {shadows: open_relighter(cache, shadows=shadows) for shadows in args.shadows}
    print("scene,edit,width,height,supersampling,texture_samples,shadows,spp,psnr_db,rel_mse,reference_noise_psnr_db")
    for edit, layer in edits.items():
        reference_scene = load_scene(shot, lights_layer=layer, width=args.width, height=args.height)
        reference = PathTracer(reference_scene, ReferenceSettings(spp=args.spp, max_bounces=0)).render(
            find_camera(reference_scene, bundled.camera)
        )
        noise = 10 * np.log10(1.0 / max(float(np.mean(reference.variance)), 1e-20))
        for shadows, relighter in relighters.items():
            relighter.set_lights(shot_lights(relighter.description, layer))
            image = relighter.render().cpu().numpy()
            print(
                f"{args.scene},{edit},{args.width},{args.height},{args.supersampling},{args.texture_samples},"
                f"{shadows},{args.spp},{psnr(image, reference.mean):.2f},{rel_mse(image, reference.mean):.3g},"
                f"{noise:.1f}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
