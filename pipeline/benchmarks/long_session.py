"""A long lighting session: N random edits on one relighter of each method, its memory and its answers.

Every edit kind a lighting artist makes (intensity, colour, move, resize, cone and focus, light
link, shadow on/off, a light added, a light removed) is drawn at random and applied to one open
relighter, which renders after each. The resident memory is sampled along the way (anonymous
RSS, what a leak grows, and the total RSS, whose file-backed pages such as shared libraries the
kernel drops and re-reads when other processes need memory); at
checkpoints the image is compared with a freshly opened relighter's render of the same lights.

    python -m pipeline.benchmarks.long_session --edits 10000 --out docs/long_session.csv

bakes tiny caches of every method (16 x 12) into a temporary folder, runs the session on each and
writes the memory curve (method, edit, anonymous and total RSS bytes) to OUT; it prints per method the growth of the
RSS after the first tenth of the edits and the largest checkpoint difference
(`pipeline.benchmarks.fault_figures --part sessions` writes them into docs/ERRORS.md).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import random
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pipeline.bake.multiview.frames import read_view_camera
from pipeline.bake.multiview.view import view_points
from pipeline.benchmarks.tiny_caches import METHODS, bake_tiny
from relight_torch import open_cache
from relight_torch.cache.layer import read_cache_layer
from relight_torch.cache.load import load_npy
from relight_torch.io.atomic import write_text_atomic
from relight_torch.lights.light import Light, LightKind, Shadow, Shaping
from relight_torch.lights.linking import decode_paths

EDIT_KINDS = ("intensity", "colour", "move", "resize", "shaping", "link", "shadow", "add", "remove")
MAX_LIGHTS = 6
"""Lights in the rig at most: an 'add' beyond it removes one instead (the rig stays small)."""


def resident_bytes() -> int:
    """This process's resident memory (RSS) now, from /proc/self/statm."""
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def anonymous_resident_bytes() -> int:
    """This process's anonymous resident memory now (heap, tensors: RssAnon of /proc/self/status)."""
    with open("/proc/self/status") as status:
        line = next(line for line in status if line.startswith("RssAnon:"))
    return int(line.split()[1]) * 1024


def open_session(layer: Path):
    """The relighter of `layer`'s method, ready to render (a multiview one set to the cache's camera)."""
    relighter = open_cache(layer)
    description = read_cache_layer(layer)
    if description.method == "multiview":
        width, height = description.resolution
        camera = read_view_camera(description.source, None, description.camera_path, None, width, height)
        relighter.set_view(
            view_points(
                relighter.caster, relighter.occluder_objects, camera, relighter.supersampling, relighter.corner_normals
            ),
            exposure_scale=camera.exposure_scale,
        )
    return relighter


@dataclass
class Rig:
    """The session's lights and what edits draw from.

    Attributes:
        lights: light path -> light, as the relighter holds them.
        centre, size: (3,) centre and extent of the scene's bounds (world units).
        objects: the cache's object prim paths (light-link targets).
        added: lights added so far (their paths are numbered by it).
    """

    lights: dict[str, Light]
    centre: np.ndarray
    size: np.ndarray
    objects: list[str]
    added: int = 0


def new_light(rig: Rig, rng: random.Random) -> Light:
    """A sphere, rect or disk light at a random point of the scene's bounds' inner half."""
    rig.added += 1
    matrix = np.eye(4)
    matrix[:3, 3] = rig.centre + (np.array([rng.random() for _ in range(3)]) - 0.5) * 0.5 * rig.size
    kind = rng.choice([LightKind.SPHERE, LightKind.RECT, LightKind.DISK])
    scale = 0.05 * float(rig.size.max())
    return Light(
        path=f"/Session/Light{rig.added}",
        kind=kind,
        world_from_light=matrix,
        intensity=rng.uniform(1.0, 50.0) / scale**2 * 1e3,
        radius=scale,
        width=scale,
        height=scale,
    )


def random_edit(rig: Rig, rng: random.Random, kind: str) -> tuple[str, Light | None]:
    """One edit of `kind` to the rig -> (light path, the light as edited, or None when removed)."""
    if kind == "add" and len(rig.lights) >= MAX_LIGHTS:
        kind = "remove"
    if kind == "remove" and len(rig.lights) <= 1:
        kind = "add"
    if kind == "add":
        light = new_light(rig, rng)
        rig.lights[light.path] = light
        return light.path, light
    path = rng.choice(sorted(rig.lights))
    if kind == "remove":
        del rig.lights[path]
        return path, None
    light = rig.lights[path]
    if kind == "intensity":
        light = dataclasses.replace(light, intensity=light.intensity * rng.uniform(0.5, 2.0))
    elif kind == "colour":
        light = dataclasses.replace(light, color=tuple(rng.uniform(0.2, 1.0) for _ in range(3)))
    elif kind == "move":
        matrix = light.world_from_light.copy()
        matrix[:3, 3] += (np.array([rng.random() for _ in range(3)]) - 0.5) * 0.05 * rig.size
        matrix[:3, 3] = np.clip(matrix[:3, 3], rig.centre - 0.45 * rig.size, rig.centre + 0.45 * rig.size)
        light = dataclasses.replace(light, world_from_light=matrix)
    elif kind == "resize":
        factor = rng.uniform(0.7, 1.4)
        light = dataclasses.replace(
            light, radius=light.radius * factor, width=light.width * factor, height=light.height * factor
        )
    elif kind == "shaping":
        light = dataclasses.replace(
            light,
            shaping=Shaping(
                cone_angle=rng.uniform(20.0, 90.0), cone_softness=rng.uniform(0.0, 1.0), focus=rng.uniform(0.0, 4.0)
            ),
        )
    elif kind == "link":
        linked = tuple(p for p in rig.objects if rng.random() < 0.7)
        light = dataclasses.replace(light, light_link=None if rng.random() < 0.3 else linked)
    elif kind == "shadow":
        light = dataclasses.replace(light, shadow=Shadow(enable=not light.shadow.enable))
    else:
        raise ValueError(f"unknown edit kind {kind!r}")
    rig.lights[path] = light
    return path, light


@dataclass(frozen=True)
class SessionReport:
    """What a session measured.

    Attributes:
        rss: (edit number, anonymous RSS bytes) samples, the first before any edit.
        total_rss: (edit number, total RSS bytes) samples at the same edits.
        checkpoint_errors: at each checkpoint, max |image - fresh image| / max |fresh image|.
        kinds: edits made of each kind.
        seconds: wall time of the edits and their renders (checkpoints' fresh relighters excluded).
    """

    rss: list[tuple[int, int]]
    total_rss: list[tuple[int, int]]
    checkpoint_errors: list[float]
    kinds: dict[str, int]
    seconds: float

    def rss_at(self, edit: int) -> int:
        """Anonymous RSS bytes of the first sample at or after `edit`."""
        return next(bytes_ for sampled, bytes_ in self.rss if sampled >= edit)

    def growth_after_edit(self, edit: int) -> float:
        """Relative anonymous RSS growth from the sample at `edit` (`rss_at`) to the last."""
        start = self.rss_at(edit)
        return (self.rss[-1][1] - start) / start

    def growth_after(self, fraction: float = 0.1) -> float:
        """Relative anonymous RSS growth from the first sample at or after `fraction` of the edits to the last."""
        return self.growth_after_edit(math.ceil(fraction * self.rss[-1][0]))


def run_session(
    layer: Path, num_edits: int, num_checkpoints: int = 4, num_rss_samples: int = 50, seed: int = 0
) -> SessionReport:
    """`num_edits` random edits (each followed by a render) on one relighter of `layer`.

    Args:
        num_checkpoints: edits after which the image is compared with a fresh relighter's.
        num_rss_samples: RSS samples along the session.
    """
    rng = random.Random(seed)
    relighter = open_session(layer)
    description = read_cache_layer(layer)
    corners = np.asarray(load_npy(layer, description, "occluders"), np.float64).reshape(-1, 3)
    low, high = corners.min(axis=0), corners.max(axis=0)
    objects = decode_paths(load_npy(layer, description, "objectPaths"))
    rig = Rig({light.path: light for light in relighter.lights}, 0.5 * (low + high), high - low, objects)
    relighter.render()
    rss, total_rss = [(0, anonymous_resident_bytes())], [(0, resident_bytes())]
    errors, kinds = [], dict.fromkeys(EDIT_KINDS, 0)
    checkpoints = {round(num_edits * (k + 1) / num_checkpoints) for k in range(num_checkpoints)}
    every = max(1, num_edits // num_rss_samples)
    seconds = 0.0
    start = time.perf_counter()
    for edit in range(1, num_edits + 1):
        kind = rng.choice(EDIT_KINDS)
        kinds[kind] += 1
        path, light = random_edit(rig, rng, kind)
        if light is None:
            relighter.remove_light(path)
        else:
            relighter.set_light(light)
        image = relighter.render()
        if edit % every == 0 or edit == num_edits:
            rss.append((edit, anonymous_resident_bytes()))
            total_rss.append((edit, resident_bytes()))
        if edit in checkpoints:
            seconds += time.perf_counter() - start
            fresh = open_session(layer)
            fresh.set_lights(list(rig.lights.values()))
            expected = fresh.render()
            del fresh
            scale = float(expected.abs().max()) or 1.0
            errors.append(float((image - expected).abs().max()) / scale)
            start = time.perf_counter()
    return SessionReport(rss, total_rss, errors, kinds, seconds)


def run_sessions(num_edits: int, methods: tuple[str, ...] = METHODS, seed: int = 0) -> dict[str, SessionReport]:
    """`run_session` on a tiny cache of each method (baked into a temporary folder)."""
    with tempfile.TemporaryDirectory(prefix="long-session-") as temp:
        return {
            method: run_session(layer, num_edits, seed=seed) for method, layer in bake_tiny(Path(temp), methods).items()
        }


def curve_csv(reports: dict[str, SessionReport]) -> str:
    """The memory curves as CSV: method, edit, anonymous and total RSS bytes."""
    rows = ["method,edit,anonymous_rss_bytes,rss_bytes"] + [
        f"{method},{edit},{anonymous},{total}"
        for method, report in reports.items()
        for (edit, anonymous), (_, total) in zip(report.rss, report.total_rss, strict=True)
    ]
    return "\n".join(rows) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--edits", type=int, default=10_000, help="edits per method (default 10000)")
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, help="CSV of the memory curve (method, edit, rss_bytes)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    reports = run_sessions(args.edits, tuple(args.methods), args.seed)
    for method, report in reports.items():
        print(
            f"{method}: {args.edits} edits, anonymous RSS {report.rss[0][1] / 2**20:.1f} -> "
            f"{report.rss[-1][1] / 2**20:.1f} MiB, growth after the first 10 %: "
            f"{100 * report.growth_after(0.1):+.2f} %, largest checkpoint difference "
            f"{max(report.checkpoint_errors):.2e} of the image's peak"
        )
    if args.out:
        write_text_atomic(args.out, curve_csv(reports))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
