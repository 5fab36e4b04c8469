"""Torch shadow maps against Embree shadow rays on a bundled scene, per lookup and map resolution.

    python -m pipeline.benchmarks.shadow_map_accuracy SCENE --width W --height H
        [--supersampling S] [--resolutions 256 512 1024] [--lookups pcss march] [--out DIR]

Bakes the scene's direct cache and, under the shot's lights and every example light edit, asks
the first light's fixed samples (`RelightSettings().area_samples` per shading point, the
relighter's own) whether they are blocked, with Embree and with `ShadowMapVisibility` at each
(resolution, lookup). Prints one CSV row per (edit, resolution, lookup): the fraction of samples
that agree with Embree, the RMSE and mean of each point's visible fraction minus Embree's (over
the points that face the light), the PSNR of the relit image against the Embree-shadowed one,
and the CPU ms of the map build and of the lookups (this process's time, one thread).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import torch

from pipeline.bake.direct.bake import bake_direct
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES, light_edit_layers
from relight_torch.direct.images import unit_light
from relight_torch.direct.loading import shot_lights
from relight_torch.direct.relighter import open_relighter
from relight_torch.direct.settings import RelightSettings
from relight_torch.light_samples import fixed_light_samples
from relight_torch.lights.emission import sample_light
from relight_torch.metrics import psnr
from relight_torch.visibility.shadow_maps import LOOKUPS


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene", choices=sorted(SCENES))
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=160)
    parser.add_argument("--supersampling", type=int, default=2)
    parser.add_argument("--resolutions", type=int, nargs="+", default=[256, 512, 1024])
    parser.add_argument("--lookups", nargs="+", default=list(LOOKUPS), choices=LOOKUPS)
    parser.add_argument("--out", help="directory for the scene and cache (default: a temporary one)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    directory = Path(args.out or tempfile.mkdtemp(prefix="relight-shadow-maps-"))
    bundled = SCENES[args.scene]
    shot = bundled.write(directory)
    scene = load_scene(shot, width=args.width, height=args.height)
    cache = bake_direct(
        scene,
        find_camera(scene, bundled.camera),
        directory / "cache",
        args.scene,
        args.supersampling,
        texture_samples=1,
    )
    traced = open_relighter(cache)
    g = traced.gbuffer
    print(
        "scene,edit,width,height,resolution,lookup,sample_agreement,visible_rmse,visible_bias,psnr_vs_embree_db,"
        "build_ms,lookup_ms"
    )
    for edit, layer in {"shot": None, **light_edit_layers(args.scene, directory)}.items():
        lights = shot_lights(traced.description, layer)
        traced.set_lights(lights)
        expected = traced.render().numpy()
        light = dataclasses.replace(unit_light(lights[0]), shaping=None, barzel=None)
        u = fixed_light_samples(
            g.num_samples, traced.num_light_samples(light), traced.settings.seed, g.device, g.position.dtype
        )
        samples = sample_light(light, g.position, u)
        live = (
            ((samples.direction * g.geometric_normal.unsqueeze(1)).sum(-1) > 0)
            & (samples.pdf > 0)
            & torch.isfinite(samples.distance)
        )
        kept = live.any(-1)
        query = (light, g.position[kept], g.geometric_normal[kept], samples.direction[kept], samples.distance[kept])
        weight = live[kept].to(g.position.dtype)
        blocked = torch.isfinite(traced.visibility.occluder_distance(*query))
        visible = ((~blocked) * weight).sum(-1) / weight.sum(-1)
        for resolution in args.resolutions:
            for lookup in args.lookups:
                mapped = open_relighter(
                    cache, shadows="shadowmaps", settings=RelightSettings(shadow_map_resolution=resolution)
                )
                mapped.visibility.lookup = lookup
                start = time.process_time()
                mapped.visibility.depth_map(light)
                build = time.process_time() - start
                start = time.process_time()
                found = torch.isfinite(mapped.visibility.occluder_distance(*query))
                lookups = time.process_time() - start
                error = ((~found) * weight).sum(-1) / weight.sum(-1) - visible
                mapped.set_lights(lights)
                agreement = float(((found == blocked) * weight).sum() / weight.sum())
                print(
                    f"{args.scene},{edit},{args.width},{args.height},{resolution},{lookup},{agreement:.4f},"
                    f"{float(error.square().mean().sqrt()):.4f},{float(error.mean()):+.4f},"
                    f"{psnr(mapped.render().numpy(), expected):.2f},{1e3 * build:.0f},{1e3 * lookups:.0f}",
                    flush=True,
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
