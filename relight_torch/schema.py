"""Registration of the project's codeless USD schemas (package data in `relight_torch/schemas/`).

USD reads plugin metadata once, when a schema is first needed: a plugin registered after the first
stage was opened is silently too late (typed prims lose `IsA`, applied APIs lose their fallbacks and
vanish from `GetAppliedSchemas`). Every module that opens a stage therefore calls
`register_schemas()` first; calling it again does nothing.

The plugin folder is found through `importlib.resources`, so it is the same whether the package runs
from a source tree, an editable install or a wheel.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from pxr import Plug

from relight_torch.errors import RelightError

PLUGIN_NAME = "relight"
SCHEMA_PACKAGE = "relight_torch.schemas"


def schema_dir() -> Path:
    """The installed folder holding plugInfo.json, generatedSchema.usda and schema.usda.

    Raises:
        RelightError: the package is not installed as plain files (USD's plugin registry reads a
            folder on disk, not a zip archive), or plugInfo.json is missing from it.
    """
    folder = resources.files(SCHEMA_PACKAGE)
    if not isinstance(folder, Path):
        raise RelightError(f"{SCHEMA_PACKAGE}: installed as {folder!r}; USD needs the schema plugin as files on disk")
    if not (folder / "plugInfo.json").is_file():
        raise RelightError(f"{folder / 'plugInfo.json'}: relight schema plugin not found (incomplete install)")
    return folder


def register_schemas() -> None:
    """Register the schema plugin (`schema_dir()`) with USD's plugin registry (idempotent).

    Raises:
        RelightError: the plugin files are missing (see `schema_dir`).
    """
    registry = Plug.Registry()
    if registry.GetPluginWithName(PLUGIN_NAME) is not None:
        return
    registry.RegisterPlugins(str(schema_dir()))
