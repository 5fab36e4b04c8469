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


@dataclass(frozen=True)
class LayeredScene:
    """A bundled scene relit through a lights layer that adds lights its shot does not have.

    A cache is baked from the base scene; the layer (and every edit, authored over it) reaches it
    through `--lights`, as a user adds lights to a baked shot.

    Attributes:
        name: e.g. 'glossy+dome'.
        base: the `BundledScene` name the layer goes over.
        description: one line.
        write_layer: directory -> path of the lights layer (the base scene written beside it).
        light_edits: example edits, each authored over the layer (`pipeline.scenes.lights`).
    """

    name: str
    base: str
    description: str
    write_layer: Callable[[Path], Path]
    light_edits: tuple[LightEdit, ...] = field(default=())
