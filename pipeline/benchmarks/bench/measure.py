"""Measuring a method on a bench scene: `run_point` bakes one grid point and `relit_rows` relights
each of its variants under every light edit, one SweepRow per edit.

relight_ms is the median wall time of a light move re-rendered (the first light translated by
1 % or 2 % of its distance from the origin along x, alternating, so every call recomputes that
light), warm (after one untimed call), synchronised on CUDA. It is measured under the shot's
lights; the other edits' rows carry the same time (one relighter, one rig size).
"""

from __future__ import annotations

import dataclasses
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch

from pipeline.bake.adapter import MethodAdapter, format_params
from pipeline.benchmarks.bench.methods import BenchScene
from pipeline.benchmarks.rows import NAN, SweepRow
from pipeline.tracing_bench import median_seconds
from relight_torch.cache.layer import read_cache_layer
from relight_torch.direct.loading import shot_lights
from relight_torch.lights.light import Light
from relight_torch.metrics import psnr, rel_mse


def moved(light: Light, fraction: float) -> Light:
    """`light` translated by `fraction` of its distance from the origin, along x (a light edit)."""
    world_from_light = light.world_from_light.copy()
    world_from_light[0, 3] += fraction * max(float(np.linalg.norm(world_from_light[:3, 3])), 1.0)
    return dataclasses.replace(light, world_from_light=world_from_light)


def relight_ms(relighter, repeats: int = 5, device: str = "cpu", part: str = "render") -> float:
    """Median ms of moving the relighter's first light and re-rendering (see the module doc).

    `relighter` is any relighter of the shared API (`lights`, `set_light`, `set_lights`, `render`);
    `part` names the method timed after each move: 'render', or 'indirect_image' for the indirect
    part alone.
    """
    render = getattr(relighter, part)
    lights = relighter.lights
    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    calls = iter(range(1 << 30))

    def edit_and_render() -> None:
        relighter.set_light(moved(lights[0], 0.01 * (1 + next(calls) % 2)))
        render()
        sync()

    seconds = median_seconds(edit_and_render, repeats)
    relighter.set_lights(lights)
    return 1e3 * seconds


def machine_description() -> str:
    """'<CPU model>, N CPUs, T torch threads' (plus the CUDA device when there is one): what a table was measured on."""
    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as handle:
            model = next((line.split(":", 1)[1].strip() for line in handle if line.startswith("model name")), model)
    except OSError:
        pass
    cuda = f", {device_name('cuda:0')}" if torch.cuda.is_available() else ""
    return f"{model}, {os.cpu_count()} CPUs, {torch.get_num_threads()} torch threads{cuda}"


def device_name(device: str) -> str:
    """The `device` column: 'cpu' or 'cuda:0 <GPU name>'."""
    if device.startswith("cuda"):
        return f"{device} {torch.cuda.get_device_name(torch.device(device))}"
    return "cpu"


def relit_rows(
    relighter,
    layer: Path,
    scene: BenchScene,
    method: str,
    parameters: dict[str, object],
    bounces: int,
    num_bytes: float,
    bake_s: float,
) -> list[SweepRow]:
    """Relight under every edit of `scene` and compare with the `bounces`-bounce reference.

    Args:
        relighter: opened on `layer`'s cache (on `scene.device`).
        layer: the cache layer (its lights are read per edit with `shot_lights`).
        method, parameters: the row's method and params columns ('bounces' is added to params
            when absent: the comparison rows read it).
        bounces: indirect bounces the method computes (0: direct only, no indirect PSNR).
        num_bytes, bake_s: the row's cache_bytes and bake_s.

    Returns:
        one row per edit, in `scene.edits` order.
    """
    description = read_cache_layer(layer)
    params = format_params({**parameters, "bounces": parameters.get("bounces", bounces)})
    rows = []
    timing = NAN
    for edit, lights_layer in scene.edits.items():
        relighter.set_lights(shot_lights(description, lights_layer))
        image = relighter.render().cpu().numpy()
        reference = scene.references.full(edit, bounces)
        indirect = (
            psnr(relighter.indirect_image().cpu().numpy(), scene.references.indirect(edit, bounces))
            if bounces > 0
            else NAN
        )
        if edit == "shot":
            timing = relight_ms(relighter, scene.repeats, scene.device)
        rows.append(
            SweepRow(
                method,
                scene.name,
                scene.width,
                scene.height,
                edit,
                params,
                psnr(image, reference),
                indirect,
                rel_mse(image, reference),
                float(num_bytes),
                bake_s,
                timing,
                device_name(scene.device),
            )
        )
    return rows


def run_point(adapter: MethodAdapter, scene: BenchScene, point: dict[str, object]) -> list[SweepRow]:
    """Bake `point` in `scene.cache_dir`, then one row per (variant, light edit); bake_s is the bake's."""
    stage, camera = scene.load()
    directory = scene.cache_dir(adapter.name, point)
    directory.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    layer = adapter.bake(stage, camera, directory, scene.name, point, scene.supersampling, scene.texture_samples)
    bake_s = time.perf_counter() - start
    return [
        row
        for variant in adapter.variants(layer, point, scene.device)
        for row in relit_rows(
            variant.relighter,
            layer,
            scene,
            adapter.name,
            variant.parameters,
            adapter.bounces(point),
            variant.cache_bytes,
            bake_s,
        )
    ]
