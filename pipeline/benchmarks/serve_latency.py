"""Edit-to-frame-on-screen latency of `relight serve`, measured in the browser.

    python -m pipeline.benchmarks.serve_latency [--width 640 --height 480] [--edits 15]
        [--screenshot docs/serve.png]

bakes the bundled Cornell box (direct method) at WIDTH x HEIGHT into a temporary folder, serves it
on this machine, opens the page in headless chromium (`pipeline.benchmarks.browser`) and, for each
edit kind (a colour change, an intensity change, a light move), sends EDITS edits from the page
itself (`fetch` of the documented PATCH) and times each from the request to the `load` of the
frame image that shows it (`window.relight.displayedAt`). Prints the median and the spread per
kind, in ms. A benchmark, not a test: figures depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

from pipeline.bake.direct.bake import bake_direct
from pipeline.benchmarks.browser import chromium_page
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES
from pipeline.serve.app import create_app
from pipeline.serve.server import serving
from pipeline.serve.session import Session

SCENE = "cornell_box"
TOKEN = "benchmark"
# One timed edit from inside the page: PATCH, then wait until the frame of the returned version is
# on screen. Resolves to milliseconds.
EDIT_JS = """async ([path, values]) => {
  const start = performance.now();
  const response = await fetch(`/api/lights${path}`, { method: "PATCH", body: JSON.stringify(values),
    headers: { "Authorization": "Bearer TOKEN", "Content-Type": "application/json" } });
  const { version } = await response.json();
  while (window.relight.displayedVersion < version) await new Promise((r) => setTimeout(r, 0));
  return window.relight.displayedAt - start;
}""".replace("TOKEN", TOKEN)


def edits(kind: str, light: dict, count: int) -> list[dict]:
    """`count` distinct edits of one kind on `light` (its attributes as GET /api/lights gives them)."""
    attributes = light["attributes"]
    out = []
    for i in range(count):
        t = (i + 1) / count
        if kind == "colour":
            out.append({"inputs:color": [1.0, 1.0 - 0.5 * t, 0.5 + 0.5 * t]})
        elif kind == "intensity":
            out.append({"inputs:intensity": attributes["inputs:intensity"] * (0.5 + t)})
        else:  # move: the light slides along its local X axis
            matrix = [row[:] for row in attributes["xformOp:transform"]]
            matrix[3][0] += 0.05 * (t - 0.5)
            out.append({"xformOp:transform": matrix})
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--edits", type=int, default=15, help="timed edits per kind")
    parser.add_argument("--screenshot", metavar="PNG", help="also save a screenshot of the page")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="relight-serve-bench-") as folder:
        shot = SCENES[SCENE].write(Path(folder) / "scene")
        scene = load_scene(shot, width=args.width, height=args.height)
        layer = bake_direct(scene, find_camera(scene, SCENES[SCENE].camera), Path(folder) / "cache", SCENE)
        session = Session.open(layer, out_dir=folder)
        try:
            with (
                serving(create_app(session, TOKEN)) as base,
                chromium_page(f"{base}/?token={TOKEN}", 1400, 820) as page,
            ):
                light = session.state()["lights"][0]
                print(f"{SCENE} {args.width}x{args.height}, {len(session.state()['lights'])} lights, cpu")
                for kind in ("colour", "intensity", "move"):
                    page.evaluate(EDIT_JS, [light["path"], edits(kind, light, 1)[0]])  # warm-up
                    times = [page.evaluate(EDIT_JS, [light["path"], edit]) for edit in edits(kind, light, args.edits)]
                    quartiles = statistics.quantiles(times, n=4)
                    print(
                        f"{kind:9s} median {statistics.median(times):7.1f} ms  "
                        f"(quartiles {quartiles[0]:.1f} .. {quartiles[2]:.1f}, {len(times)} edits)"
                    )
                if args.screenshot:
                    page.screenshot(path=args.screenshot)
                    print(f"wrote {args.screenshot}")
        finally:
            session.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
