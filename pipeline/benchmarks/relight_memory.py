"""Memory and speed of the direct relighter on a baked cache: what a lighting session holds.

    python -m pipeline.benchmarks.relight_memory CACHE [--memory-budget GB] [--repeats N]

Opens CACHE with the shot's lights, renders the first frame, then times `repeats` moves of one
light (a translation: its transport is traced again) and `repeats` colour edits of it (a
rescale), each followed by `render()`. Prints one line per figure: open and first-frame seconds,
median wall and CPU ms of each edit, the bytes the relighter's per-light caches hold, and the
process's resident set size (the whole process: torch, Embree, the G-buffer) after opening and
after the first frame, with its peak by then (`*_peak_rss_gb`: what opening, the first frame,
and the whole session needed at most). On a shared machine the wall times count other people's
work; the CPU times do not.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from pipeline.benchmarks.peak_rss import peak_rss_bytes, rss_bytes
from pipeline.benchmarks.stopwatch import Stopwatch
from pipeline.heap import use_one_heap_arena
from relight_torch.direct.relighter import open_relighter
from relight_torch.direct.settings import RelightSettings


def measure(cache: str, memory_budget: float | None, repeats: int) -> dict[str, float | int | str]:
    """The figures of the module doc for one cache; `memory_budget` in bytes (None: the default)."""
    settings = RelightSettings(memory_budget=None if memory_budget is None else int(memory_budget))
    start = time.perf_counter()
    relighter = open_relighter(cache, settings=settings)
    opened = time.perf_counter() - start
    open_rss, open_peak = rss_bytes(), peak_rss_bytes()
    relighter.render()
    first = time.perf_counter() - start - opened
    first_rss, first_peak = rss_bytes(), peak_rss_bytes()
    light = next(light for light in relighter.lights if light.kind.value == "SphereLight")
    moves, colours = Stopwatch(), Stopwatch()
    rng = np.random.default_rng(0)
    for _ in range(repeats):
        transform = light.world_from_light.copy()
        transform[:3, 3] += rng.uniform(-0.05, 0.05, 3)
        light = dataclasses.replace(light, world_from_light=transform)
        with moves.section():
            relighter.set_light(light)
            relighter.render()
    for k in range(repeats):
        light = dataclasses.replace(light, color=(1.0, 0.5 + 0.4 * (k % 2), 0.3))
        with colours.section():
            relighter.set_light(light)
            relighter.render()
    height, width = relighter.gbuffer.image_size
    move_wall, move_cpu = moves.median_ms()
    colour_wall, colour_cpu = colours.median_ms()
    return {
        "sub_samples": relighter.gbuffer.num_samples,
        "sub_image": f"{width}x{height}",
        "lights": len(relighter.lights),
        "open_s": opened,
        "first_frame_s": first,
        "move_ms": move_wall,
        "move_cpu_ms": move_cpu,
        "colour_ms": colour_wall,
        "colour_cpu_ms": colour_cpu,
        "cache_mb": relighter.cache_bytes() / 1e6,
        "open_rss_gb": open_rss / 1e9,
        "open_peak_rss_gb": open_peak / 1e9,
        "first_frame_rss_gb": first_rss / 1e9,
        "first_frame_peak_rss_gb": first_peak / 1e9,
        "peak_rss_gb": peak_rss_bytes() / 1e9,
    }


def main() -> None:
    use_one_heap_arena()  # as `relight render` does (pipeline/heap.py)
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("cache")
    parser.add_argument("--memory-budget", type=float, metavar="GB", help="RelightSettings.memory_budget in GB")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    budget = None if args.memory_budget is None else args.memory_budget * 1e9
    for name, value in measure(args.cache, budget, args.repeats).items():
        print(f"{name}: {value:.3f}" if isinstance(value, float) else f"{name}: {value}")


if __name__ == "__main__":
    main()
