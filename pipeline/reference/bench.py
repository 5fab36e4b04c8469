"""Throughput of the reference path tracer on the bundled Cornell box.

    python -m pipeline.reference.bench [--size 128] [--spp 16] [--workers N]

Renders the Cornell box at size x size, direct light only (max bounces 0) and with full global
illumination (max bounces 4), and prints paths per second (camera paths, the unit of `spp`),
samples per second (surface vertices shaded: next-event estimation plus BSDF sampling at each)
and CPU microseconds per path. Wall-clock figures depend on what else the machine runs; the CPU
figure much less so.
"""

from __future__ import annotations

import argparse
import tempfile
import time

from pipeline.reference.path_tracer import PathTracer, ReferenceSettings
from pipeline.scene import Camera, find_camera, load_scene
from pipeline.scenes import SCENES


def measure(tracer: PathTracer, camera: Camera) -> dict[str, float]:
    """Render once: wall and CPU seconds, paths/s and shaded vertices (samples)/s."""
    cpu_start = time.process_time()
    image = tracer.render(camera)
    cpu_seconds = time.process_time() - cpu_start
    return {
        "seconds": image.seconds,
        "paths_per_second": image.num_paths / image.seconds,
        "samples_per_second": image.num_vertices / image.seconds,
        "cpu_us_per_path": cpu_seconds / image.num_paths * 1e6,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=128, help="image width and height (default 128)")
    parser.add_argument("--spp", type=int, default=16, help="samples per pixel (default 16)")
    parser.add_argument("--workers", type=int, default=None, help="worker threads (default: CPUs available)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as directory:
        bundled = SCENES["cornell_box"]
        scene = load_scene(str(bundled.write(directory)), width=args.size, height=args.size)
    camera = find_camera(scene, bundled.camera)
    for label, max_bounces in (("direct", 0), ("GI", 4)):
        settings = ReferenceSettings(spp=args.spp, max_bounces=max_bounces, num_workers=args.workers)
        tracer = PathTracer(scene, settings)
        figures = measure(tracer, camera)
        print(
            f"cornell_box {args.size}x{args.size} {args.spp} spp {label} (max bounces {max_bounces}), "
            f"{tracer.num_workers} workers: {figures['seconds']:.2f} s, "
            f"{figures['paths_per_second'] / 1e6:.3f} M paths/s, "
            f"{figures['samples_per_second'] / 1e6:.3f} M samples/s, "
            f"{figures['cpu_us_per_path']:.2f} CPU us/path"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
