"""An exterior shot with open sky, written at test time (`pipeline.benchmarks.suite_assets.
write_exterior_shot`): instanced and point-instanced Utah teapots (tests/data/scene/usdwg_teapot,
CC0) on a floor, a distant light and coloured sphere lights, with cameras that see the horizon
(top half sky), only sky, a single teapot close up, and the inside of a closed box.

`python -m tests.sky_support DIR [--teapots N]` writes the same shot for measurements (the issue's
production case is about a thousand teapots and sixteen sphere lights).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from pipeline.benchmarks.suite_assets import CAMERAS, TEAPOT, write_exterior_shot

__all__ = ["CAMERAS", "TEAPOT", "write_exterior_shot"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("directory", type=Path)
    parser.add_argument("--teapots", type=int, default=1000)
    parser.add_argument("--sphere-lights", type=int, default=16)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    args = parser.parse_args()
    print(write_exterior_shot(args.directory, args.teapots, args.sphere_lights, args.width, args.height))


if __name__ == "__main__":
    main()
