#!/usr/bin/env bash
# Packaging smoke check: build the wheel from the tracked files (what a clean clone holds), install it
# with its pinned dependencies into a fresh virtual environment that sees no system site-packages,
# then, from an empty directory with no source tree on the path, run the CLI: version, bundled
# scenes, a 16x16 bake of the Cornell box, a render of it and a `relight serve` session of it.
#
# Environment: PYTHON (default python3.11); TORCH_INDEX_URL (empty: pip's configured index; set it
# to PyTorch's CPU-only wheel index to avoid the CUDA build, as the README says).
set -euo pipefail

repo="$(cd "$(dirname "$0")/.." && pwd)"
python="${PYTHON:-python3.11}"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT

step() { printf 'wheel_smoke [%3ds]: %s\n' "$SECONDS" "$*"; }

step "copying the tracked files"
mkdir "$work/src" "$work/dist" "$work/run"
(cd "$repo" && git ls-files -z | tar --null -T - -cf -) | tar -xf - -C "$work/src"

step "creating a fresh venv (no system site-packages)"
"$python" -m venv "$work/venv"
bin="$work/venv/bin"

step "building the wheel"
"$bin/pip" wheel --quiet --no-deps --wheel-dir "$work/dist" "$work/src"
wheel=("$work"/dist/relight-*.whl)

step "installing torch==2.13.0${TORCH_INDEX_URL:+ from $TORCH_INDEX_URL}, then $(basename "${wheel[0]}")"
"$bin/pip" install --quiet --no-compile ${TORCH_INDEX_URL:+--index-url "$TORCH_INDEX_URL"} torch==2.13.0
"$bin/pip" install --quiet --no-compile "${wheel[0]}"
rm -rf "$work/src"    # nothing of the source tree is left to import from

cd "$work/run"
export PYTHONPATH=""
step "running relight from $(pwd)"
"$bin/relight" --version
"$bin/python" - <<'PY'
import importlib.metadata
import pathlib

import relight_torch
from relight_torch.schema import schema_dir

site = pathlib.Path(relight_torch.__file__).resolve().parents[1]
assert site.name == "site-packages", f"relight_torch imported from {site}, not the installed wheel"
assert relight_torch.__version__ == importlib.metadata.version("relight"), relight_torch.__version__
assert (schema_dir() / "plugInfo.json").is_file() and site in schema_dir().parents, schema_dir()
PY
"$bin/relight" scenes list
"$bin/relight" scenes write scenes > /dev/null
"$bin/relight" bake scenes/cornell_box.usda --camera /World/Camera --width 16 --height 16 --method direct \
    --supersampling 1 --texture-samples 1 --out cache
"$bin/relight" render cache/cornell_box.relight.usda -o frame.exr --png frame.png
"$bin/python" - <<'PY'
import numpy as np

from relight_torch.io.exr import read_rgb_exr

rgb = read_rgb_exr("frame.exr")
assert rgb.shape == (16, 16, 3), rgb.shape
assert np.isfinite(rgb).all() and float(rgb.mean()) > 0, "the rendered frame is black or not finite"
PY
step "serving the cache: the page and a frame"
"$bin/python" - "$bin/relight" <<'PY'
import subprocess
import sys
import urllib.request

server = subprocess.Popen([sys.argv[1], "serve", "cache/cornell_box.relight.usda"], stdout=subprocess.PIPE, text=True)
try:
    url = server.stdout.readline().split(": ", 2)[-1].strip()
    assert "/?token=" in url, url
    page = urllib.request.urlopen(url, timeout=60).read().decode()
    assert "<title>relight serve</title>" in page, page[:200]
    frame = urllib.request.urlopen(url.replace("/?token=", "/api/frame.png?token="), timeout=60).read()
    assert frame.startswith(b"\x89PNG"), frame[:8]
finally:
    server.terminate()
    server.wait(30)
PY
step "ok"
