"""Regenerate the codeless schema plugin from schema.usda.

Run after editing relight_torch/schemas/schema.usda:

    .venv/bin/python -m relight_torch.schemas.generate

It runs `python -m pxr.Usd.usdGenSchema schema.usda <this folder>` (needs jinja2), which writes
generatedSchema.usda and plugInfo.json (no C++: the GLOBAL prim sets skipCodeGeneration), then
replaces the generator's build-system placeholders in plugInfo.json so the folder is a resource-only
plugin that `Plug.Registry().RegisterPlugins` loads from where it lies.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

SCHEMA_DIR = Path(__file__).resolve().parent
PLACEHOLDERS = {
    "@PLUG_INFO_LIBRARY_PATH@": "",
    "@PLUG_INFO_RESOURCE_PATH@": ".",
    "@PLUG_INFO_ROOT@": ".",
}


def generate(output_dir: Path) -> None:
    """Write generatedSchema.usda and plugInfo.json for schema.usda into `output_dir`.

    Raises:
        subprocess.CalledProcessError: usdGenSchema failed (its message is on stderr).
    """
    subprocess.run(
        [sys.executable, "-m", "pxr.Usd.usdGenSchema", str(SCHEMA_DIR / "schema.usda"), str(output_dir)],
        check=True,
        capture_output=True,
        text=True,
    )
    plug_info = output_dir / "plugInfo.json"
    text = plug_info.read_text()
    for placeholder, value in PLACEHOLDERS.items():
        text = text.replace(placeholder, value)
    plug_info.write_text(text)


def main() -> int:
    """Regenerate the plugin files beside schema.usda; return the process exit status."""
    try:
        generate(SCHEMA_DIR)
    except subprocess.CalledProcessError as error:
        print(error.stderr, file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
