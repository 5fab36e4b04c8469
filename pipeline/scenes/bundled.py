"""What a bundled scene is: a name, its camera, a description, a writer and example light edits."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path


@dataclass(frozen=True)
class LightOverride:
    """New values for some attributes of one light prim, authored as an `over` in a lights layer.

    Attributes:
        prim_path: the light prim in the scene, e.g. '/World/Lights/Key'.
        values: attribute name -> (Sdf value type name, e.g. 'float3', 'color3f', value).
        api_schemas: API schemas to apply on the over (e.g. ('ShapingAPI',)).
    """

    prim_path: str
    values: dict[str, tuple[str, object]]
    api_schemas: tuple[str, ...] = ()


@dataclass(frozen=True)
class LightEdit:
    """A named example light edit over a bundled scene ('move', 'reaim_spot', ...)."""

    name: str
    description: str
    overrides: tuple[LightOverride, ...]


@dataclass(frozen=True)
class BundledScene:
    """A test/demo scene authored by a script in the repository.

    Attributes:
        name: scene name; `write` writes DIR/<name>.usda.
        camera: the camera prim path to render from.
        description: one line for `relight scenes list`.
        write: directory -> path of the written .usda (textures beside it, relative asset paths).
        light_edits: example light edits over the scene's lights (see `pipeline.scenes.lights`).
    """

    name: str
    camera: str
    description: str
    write: Callable[[Path], Path]
    light_edits: tuple[LightEdit, ...] = field(default=())
