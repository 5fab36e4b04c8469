"""The first frame after each edit kind, on every cache given: CPU and wall ms, its level, and its
PSNR against the converged frame.

    python -m pipeline.benchmarks.first_frame --shot-cache L --direct-cache L [--cache L ...] --work DIR
        [--threads 2] [--repeats 7] [--edits KIND ...] [--out docs/bench/progressive/first_frame.md]

The Cornell box of `pipeline.benchmarks.progressive` (`prepare`: its scene, lights and light edits)
with the caches given at their baked size: the shot cache, the direct cache and any more (--cache:
e.g. a cuts cache, whose relighter has material edits, and a multiview cache, which renders from any
camera). Edit kinds: the light edits of `progressive.edit_rigs` (colour, shaping, move, new light,
dome turn), a material's diffuse colour and roughness, and a camera move. A cache whose relighter
lacks what an edit kind needs is listed as such from its declared capability
(`progressive.unsupported`): `material_edits` for a material edit, its method's `needs_view`
(`relight_torch.methods`) for a camera move; an edit its relighter refuses (`RelightError`) is
listed with the refusal.

Per cache and edit kind: an untimed edit, then --repeats edits, each from a warm relighter (the
state before it rendered). Timed by the process's CPU clock (all threads) and the wall clock, from
the edit's call to its first frame: with `progressive` set, `progressive_frames`' first frame at the
coarsest level (budget 0, a fresh cost model), then refined to the exact frame for the PSNR; without
it, `render()`, the exact frame itself ('whole' in the level column). A camera move's frames are
`camera_move_frames` (`pipeline.bake.multiview.frames`): the new view traced, matched and relit at
one pixel per 16 x 16 first, its primary rays and correspondence map included in the time.
Prints one markdown row per cache and edit (median CPU ms, median wall ms, median dB); with --out
also writes them, with this command, the machine and its load average, to that file.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pipeline.bake.multiview.frames import camera_move_frames, read_view_camera, set_camera
from pipeline.benchmarks import run_in_work
from pipeline.benchmarks.bench.measure import machine_description
from pipeline.benchmarks.progressive import EDITS, LIGHT_EDITS, Setup, prepare, unsupported
from pipeline.scene.types import Camera
from relight_torch import open_cache
from relight_torch.cache.layer import CacheDescription, read_cache_layer
from relight_torch.errors import RelightError
from relight_torch.io.atomic import write_text_atomic
from relight_torch.methods import relight_method
from relight_torch.metrics import psnr
from relight_torch.multiview.relighter import MultiviewRelighter
from relight_torch.progressive import CostModel, level_label, progressive_frames
from relight_torch.protocol import CacheRelighter

MATERIAL = 0
"""The material the material edits change: the first one (its roughness edits cross GLOSSY_ROUGHNESS: every
point of it changes its samples, the worst case)."""
CAMERA_STEP = 0.01
"""A camera move: the camera translated along its x axis by this fraction of its distance from the origin."""


Frames = Iterator[tuple[str, torch.Tensor]]
"""An edit's frames, first to converged, as (level, (H, W, 3) image): '1/p' (one shaded point per p x p
pixels), 'exact', or 'whole' (the one exact frame of a relighter without progressive refinement)."""


@dataclass
class Session:
    """One cache's relighter and, where its method `needs_view`, the camera it was baked for (at
    its size), which camera moves start from.

    Attributes:
        relighter: the cache's relighter (set to the cache's camera where it needs a view).
        camera: the cache's camera where the method needs a view, else None.
    """

    relighter: CacheRelighter
    camera: Camera | None

    @classmethod
    def open(cls, layer: Path, description: CacheDescription) -> Session:
        session = cls(open_cache(layer), None)
        if relight_method(description.method).needs_view:
            width, height = description.resolution
            session.camera = read_view_camera(description.source, None, description.camera_path, None, width, height)
            set_camera(session.view_relighter, session.camera)
        return session

    @property
    def view_relighter(self) -> MultiviewRelighter:
        """The relighter, of a method that `needs_view`."""
        assert isinstance(self.relighter, MultiviewRelighter), "only a relighter that needs a view moves its camera"
        return self.relighter

    def moved_camera(self, fraction: float) -> Camera:
        """The cache's camera translated along its x axis by `fraction` of its distance from the origin."""
        assert self.camera is not None, "a camera move needs a view"
        world_from_camera = self.camera.world_from_camera.copy()
        distance = max(float(np.linalg.norm(world_from_camera[:3, 3])), 1.0)
        world_from_camera[:3, 3] += fraction * distance * world_from_camera[:3, 0]
        return dataclasses.replace(self.camera, world_from_camera=world_from_camera)


def relighter_frames(relighter: CacheRelighter) -> Frames:
    """The frames after an edit: a progressive relighter's levels from the coarsest (budget 0, a
    fresh cost model), else its `render()`."""
    if not relighter.progressive:
        yield "whole", relighter.render()
        return
    for frame in progressive_frames(relighter, 0.0, costs=CostModel()):
        yield level_label(frame.stride), frame.image


@dataclass(frozen=True)
class Edit:
    """One edit kind: the state before its k-th repetition, and the edit with its frames (timed
    from the edit's call to the first frame).

    Attributes:
        before: (session, k) -> None, the state before the edit.
        frames: (session, k) -> the edit made, then its `Frames`.
    """

    before: Callable[[Session, int], None]
    frames: Callable[[Session, int], Frames]


def _edited(make: Callable[[Session, int], None]) -> Callable[[Session, int], Frames]:
    """The frames of an edit of the rig or the materials: `make`, then the relighter's frames."""

    def frames(session: Session, k: int) -> Frames:
        make(session, k)
        yield from relighter_frames(session.relighter)

    return frames


def edits(setup: Setup) -> dict[str, Edit]:
    """Edit kind -> its `Edit`, different for each repetition k."""
    table: dict[str, Edit] = {}
    for name in LIGHT_EDITS:
        rigs = setup.rigs[name]
        table[name] = Edit(
            lambda s, k, rigs=rigs: s.relighter.set_lights(rigs(k)[0]),
            _edited(lambda s, k, rigs=rigs: s.relighter.set_lights(rigs(k)[1])),
        )
    lights = setup.rigs["colour"](0)[0]

    def material(values: Callable[[int], dict[str, object]], after: Callable[[int], dict[str, object]]) -> Edit:
        def before(session: Session, k: int) -> None:
            session.relighter.set_lights(lights)
            session.relighter.edit_material(MATERIAL, **values(k))

        return Edit(before, _edited(lambda s, k: s.relighter.edit_material(MATERIAL, **after(k))))

    table["material colour"] = material(
        lambda k: {"diffuse_color": (0.6, 0.6, 0.6 - 0.01 * k)}, lambda k: {"diffuse_color": (0.2, 0.6, 0.3 - 0.01 * k)}
    )
    table["material roughness"] = material(
        lambda k: {"roughness": 0.3 + 0.01 * k}, lambda k: {"roughness": 0.6 + 0.01 * k}
    )

    def camera_before(session: Session, k: int) -> None:
        session.relighter.set_lights(lights)
        set_camera(session.view_relighter, session.moved_camera(CAMERA_STEP * k))

    def camera_frames(session: Session, k: int) -> Frames:
        moves = camera_move_frames(session.view_relighter, session.moved_camera(CAMERA_STEP * (k + 1)))
        for stride, image in moves:
            yield level_label(stride), image

    table["camera move"] = Edit(camera_before, camera_frames)
    return table


def measure(session: Session, edit: Edit, repeats: int) -> tuple[float, float, float, str]:
    """(median CPU ms, median wall ms, median dB vs converged, level) of the first frame of
    `repeats` edits after an untimed one."""
    cpu_ms, wall_ms, db, levels = [], [], [], []
    for k in range(repeats + 1):
        edit.before(session, k)
        session.relighter.render()
        cpu, wall = time.process_time(), time.perf_counter()
        frames = edit.frames(session, k)
        level, image = next(frames)
        cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
        converged = ([image] + [later for _, later in frames])[-1]
        if k:
            cpu_ms.append(1e3 * cpu)
            wall_ms.append(1e3 * wall)
            db.append(psnr(image.cpu().numpy(), converged.cpu().numpy()))
            levels.append(level)
    return statistics.median(cpu_ms), statistics.median(wall_ms), statistics.median(db), statistics.mode(levels)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--shot-cache", type=Path, required=True)
    parser.add_argument("--direct-cache", type=Path, required=True)
    parser.add_argument(
        "--cache", type=Path, nargs="+", default=[], help="more caches of the Cornell box (e.g. cuts, multiview)"
    )
    parser.add_argument("--threads", type=int, default=2, help="torch threads")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--edits", nargs="+", choices=EDITS, default=list(EDITS), metavar="EDIT")
    parser.add_argument("--work", type=Path, help="the scene and the new light's layer (default: temporary)")
    parser.add_argument("--out", type=Path, help="also write the table, the command and the machine here (markdown)")
    args = parser.parse_args(argv)
    args.command = " ".join(sys.argv[1:] if argv is None else argv)
    torch.set_num_threads(args.threads)
    return run_in_work(args.work, lambda work: _run(args, work))


def _run(args: argparse.Namespace, work: Path) -> int:
    # `prepare` reads the image size from the arguments only to bake; the caches are given.
    setup = prepare(
        argparse.Namespace(width=0, height=0, shot_cache=args.shot_cache, direct_cache=args.direct_cache), work
    )
    table = edits(setup)
    load = os.getloadavg()[0]
    rows = ["| cache | edit | level | CPU ms | wall ms | dB vs converged |", "|---|---|---|---|---|---|"]
    print("\n".join(rows))
    caches = [(setup.shot_label, setup.shot_layer), ("direct", setup.direct_layer)]
    for layer in args.cache:
        caches.append((read_cache_layer(layer).method, layer))
    for label, layer in caches:
        description = read_cache_layer(layer)
        session = Session.open(layer, description)
        for name in args.edits:
            reason = unsupported(session.relighter, description.method, name)
            if reason is None:
                try:
                    cpu, wall, db, level = measure(session, table[name], args.repeats)
                except RelightError as error:
                    reason = f"refused: {error}"
            if reason is not None:
                rows.append(f"| {label} | {name} | not supported: {reason} |  |  |  |")
            else:
                rows.append(f"| {label} | {name} | {level} | {cpu:.1f} | {wall:.1f} | {db:.1f} |")
            print(rows[-1], flush=True)
        del session
    if args.out is not None:
        command = f"python -m pipeline.benchmarks.first_frame {args.command}"
        write_text_atomic(
            args.out,
            "# The first frame after an edit, at the caches' size\n\n"
            f"Generated by `{command}`. Median of {args.repeats} edits after an untimed one, from the edit's "
            "call to its first frame: a progressive relighter's coarsest level (1/p: one shaded point per p x p "
            "pixels, upsampled edge-aware), else its whole frame (`render()`, exact); a camera move includes "
            "its primary rays and correspondence map. dB: the first frame's PSNR against the converged frame "
            "(inf: exact). An edit kind a cache's relighter has no capability for is listed as not supported.\n\n"
            + "\n".join(rows)
            + f"\n\nMachine: {machine_description()}; load average {load:.1f} / {os.getloadavg()[0]:.1f} "
            "(1 min, start / end).\n",
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
