"""Registration of the project's codeless USD schemas (`schemas/` at the repository root).

USD reads plugin metadata once, when a schema is first needed: a plugin registered after the first
stage was opened is silently too late (typed prims lose `IsA`, applied APIs lose their fallbacks and
vanish from `GetAppliedSchemas`). Every module that opens a stage therefore calls
`register_schemas()` first; calling it again does nothing.
"""

from __future__ import annotations

from pathlib import Path

from pxr import Plug

SCHEMA_DIR = Path(__file__).resolve().parents[1] / "schemas"
PLUGIN_NAME = "relight"


def register_schemas() -> None:
    """Register `schemas/plugInfo.json` with USD's plugin registry (idempotent).

    Raises:
        FileNotFoundError: the schemas folder is missing (an incomplete checkout or install).
    """
    registry = Plug.Registry()
    if registry.GetPluginWithName(PLUGIN_NAME) is not None:
        return
    if not (SCHEMA_DIR / "plugInfo.json").is_file():
        raise FileNotFoundError(f"{SCHEMA_DIR / 'plugInfo.json'}: relight schema plugin not found")
    registry.RegisterPlugins(str(SCHEMA_DIR))
