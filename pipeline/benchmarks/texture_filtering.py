"""Where direct relighting's error lives on a textured, normal-mapped scene, and what filtering costs.

    python -m pipeline.benchmarks.texture_filtering [SCENE] --width W --height H --spp N
        [--variants S:T ...] [--out DIR]

Renders the shot's reference once (max-bounces 0, box-filtered pixels), then for each variant
S:T (supersampling S, texture samples T) bakes the direct cache, relights the shot and every
example light edit, and prints one CSV row per variant, edit and pixel class:

* ``edge``: the pixel covers more than one object (silhouettes, contacts), seen on a 4 x 4 grid;
* ``textured``: one object whose material reads a texture (albedo and/or normal map);
* ``plain``: one object with constant material inputs.

Errors are measured as `relight_torch.metrics.psnr` does (linear RGB clamped to [0, 1]). Each row
gives the class's pixel count, its share of the image's squared error, its PSNR, the share of the
image's squared error that the reference's own variance explains over the class, the
bake's time and the cache's size. Timings on a loaded machine are noisy: take medians of repeats.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from pipeline.bake.deep_framebuffer import grid_rays, texel_density
from pipeline.bake.direct.bake import bake_direct
from pipeline.reference.path_tracer import PathTracer, ReferenceSettings
from pipeline.scene import find_camera, load_scene
from pipeline.scene.types import Camera, Scene
from pipeline.scenes import SCENES, light_edit_layers
from pipeline.tracing import Tracer
from relight_torch.direct.loading import shot_lights
from relight_torch.direct.relighter import open_relighter

CLASSES = ("edge", "textured", "plain")
CLASS_GRID = 4
"""Rays per pixel side used to classify pixels."""


def pixel_classes(scene: Scene, camera: Camera) -> np.ndarray:
    """(H, W) index into `CLASSES` of every pixel, from the objects seen on a 4 x 4 grid per pixel."""
    origins, directions = grid_rays(camera, CLASS_GRID)
    hits = Tracer(scene.geometry).intersect(origins, directions)
    object_id = np.where(hits.hit, scene.geometry.object_ids[np.where(hits.hit, hits.triangle_id, 0)], -1)
    material_id = np.where(hits.hit, scene.geometry.material_ids[np.where(hits.hit, hits.triangle_id, 0)], -1)
    height, width, n = camera.height, camera.width, CLASS_GRID
    per_pixel = object_id.reshape(height, n, width, n).transpose(0, 2, 1, 3).reshape(height, width, n * n)
    edge = np.any(per_pixel != per_pixel[..., :1], axis=-1)
    textured_materials = np.append(texel_density(scene) > 0, False)  # -1: no hit
    material = material_id.reshape(height, n, width, n)[:, 0, :, 0]
    return np.where(edge, 0, np.where(textured_materials[material], 1, 2))


def directory_size(path: Path) -> int:
    """Bytes of every file under `path`."""
    return sum(p.stat().st_size for p in Path(path).rglob("*") if p.is_file())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene", nargs="?", default="glossy", choices=sorted(SCENES))
    parser.add_argument("--width", type=int, default=96)
    parser.add_argument("--height", type=int, default=72)
    parser.add_argument("--spp", type=int, default=256, help="reference samples per pixel")
    parser.add_argument("--variants", nargs="+", default=["2:2"], help="S:T supersampling and texture samples")
    parser.add_argument("--edits", nargs="*", help="light edits to measure (default: the shot and every edit)")
    parser.add_argument("--out", help="directory for the scene, caches and error maps (default: a temporary one)")
    args = parser.parse_args(argv)
    directory = Path(args.out or tempfile.mkdtemp(prefix="relight-filtering-"))
    bundled = SCENES[args.scene]
    shot = bundled.write(directory)
    edits = light_edit_layers(args.scene, directory)
    if args.edits:
        edits = {name: layer for name, layer in edits.items() if name in args.edits}
    scene = load_scene(shot, width=args.width, height=args.height)
    camera = find_camera(scene, bundled.camera)
    classes = pixel_classes(scene, camera)
    references = {}
    for edit, layer in edits.items():
        reference_scene = load_scene(shot, lights_layer=layer, width=args.width, height=args.height)
        references[edit] = PathTracer(reference_scene, ReferenceSettings(spp=args.spp, max_bounces=0)).render(
            find_camera(reference_scene, bundled.camera)
        )
    print("scene,variant,edit,class,pixels,error_share,psnr_db,noise_share,bake_s,cache_bytes")
    for variant in args.variants:
        s, t = (int(v) for v in variant.split(":"))
        cache_dir = directory / f"cache_{s}_{t}"
        start = time.perf_counter()
        cache = bake_direct(scene, camera, cache_dir, args.scene, s, t)
        bake_s = time.perf_counter() - start
        size = directory_size(cache_dir)
        relighter = open_relighter(cache)
        for edit, layer in edits.items():
            relighter.set_lights(shot_lights(relighter.description, layer))
            image = relighter.render().cpu().numpy()
            reference = references[edit]
            # As relight_torch.metrics.psnr measures: linear RGB clamped to [0, 1].
            error = np.mean(np.square(np.clip(image, 0, 1) - np.clip(reference.mean, 0, 1)), axis=-1)
            noise = np.mean(np.where(reference.mean < 1.0, reference.variance, 0.0), axis=-1)
            np.save(directory / f"error_{s}_{t}_{edit}.npy", error)
            total = float(error.sum())
            for k, name in [(-1, "all")] + list(enumerate(CLASSES)):
                mask = np.ones_like(classes, bool) if k < 0 else classes == k
                mse = float(error[mask].mean()) if mask.any() else 0.0
                print(
                    f"{args.scene},{s}:{t},{edit},{name},{int(mask.sum())},{error[mask].sum() / total:.3f},"
                    f"{10 * np.log10(1.0 / max(mse, 1e-20)):.2f},{noise[mask].sum() / total:.3f},"
                    f"{bake_s:.1f},{size}",
                    flush=True,
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
