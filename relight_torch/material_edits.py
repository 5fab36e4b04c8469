"""Material edits: UsdPreviewSurface inputs set to constants on one material's shading points, and
the USD layers that carry them.

The relighters that edit materials (the direct relighter, and through it the cuts') take their
inputs through `apply_material_edit`, so that an input name, a value's shape and the inputs refused
mean the same everywhere. A materials layer is read by `layer_material_edits` (`relight render`,
`relight serve` and a session's load) and written by `write_material_edits` (a session's save), on
the attribute that gives each shader input its value.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping

import torch
from pxr import Gf, Sdf, Usd, UsdShade

from relight_torch.brdf.preview_surface import USD_INPUT_FIELDS, PreviewSurfaceParams
from relight_torch.cache.layer import CacheDescription
from relight_torch.errors import RelightError
from relight_torch.protocol import CacheRelighter
from relight_torch.stage import open_layer, open_stage, time_code

COLOUR_INPUTS = frozenset({"diffuse_color", "specular_color", "metallic", "ior", "use_specular_workflow"})
"""Inputs that reach reflected light only through the colours of the BRDF's split factors
(`preview_surface.factor_colours`): editing them re-weights kept factors and traces nothing."""

FACTOR_COLOUR_INPUTS = COLOUR_INPUTS | {"clearcoat"}
"""Inputs the colours of the split factors depend on (`preview_surface.factor_colours`)."""

REFUSED_INPUTS = {"opacity": "opacity changes the shadows the occluders cast, which the cache baked; re-bake the cache"}
"""Inputs a relighter cannot edit, and why."""


@dataclasses.dataclass(frozen=True)
class MaterialChange:
    """What differs between two sets of material parameters of the same shading points.

    Attributes:
        inputs: the names of the inputs that differ somewhere.
        rows: (N,) bool, the shading points where any input differs.
    """

    inputs: frozenset[str]
    rows: torch.Tensor

    @property
    def colour_only(self) -> bool:
        """Whether every changed input is a `COLOUR_INPUTS` one."""
        return self.inputs <= COLOUR_INPUTS

    @classmethod
    def between(cls, old: PreviewSurfaceParams, new: PreviewSurfaceParams) -> MaterialChange:
        """The change from `old` to `new` (same rows, device and dtype).

        Raises:
            RelightError: a `REFUSED_INPUTS` input differs, or the rows differ in number.
        """
        if new.opacity.shape != old.opacity.shape:
            raise RelightError(f"material parameters must have {old.opacity.shape[0]} rows, got {new.opacity.shape[0]}")
        rows = torch.zeros(old.opacity.shape, dtype=torch.bool, device=old.opacity.device)
        inputs = set()
        for item in dataclasses.fields(old):
            differs = getattr(old, item.name) != getattr(new, item.name)
            differs = differs.any(-1) if differs.dim() > 1 else differs
            if bool(differs.any()):
                if item.name in REFUSED_INPUTS:
                    raise RelightError(f"{item.name}: {REFUSED_INPUTS[item.name]}")
                inputs.add(item.name)
                rows |= differs
        return cls(frozenset(inputs), rows)


def check_material_values(material: str, values: Mapping[str, object]) -> None:
    """Check inputs as `apply_material_edit` does, without shading points (an edit to keep for later).

    Raises:
        RelightError: as `apply_material_edit`, naming `material`.
    """
    apply_material_edit(PreviewSurfaceParams.zeros(0), torch.zeros(0, dtype=torch.int32), material, values, [material])


def prim_material_paths(material_paths: list[str]) -> list[str]:
    """The distinct material prim paths of a cache's material paths, sorted: without the pseudo
    paths of unbound gprims ('<fallback>', '<displayColor>'), which no layer can name."""
    return sorted({path for path in material_paths if path.startswith("/")})


def material_rows(material_ids: torch.Tensor, material: int | str, material_paths: list[str] | None) -> torch.Tensor:
    """(N,) bool: the shading points of `material`, a material id or a material prim path (every id
    of that path: a material bound with several displayColors has one id per colour).

    Raises:
        RelightError: a path without the cache's material paths, or one the cache does not have.
    """
    if isinstance(material, int):
        return material_ids == material
    if material_paths is None:
        raise RelightError(f"material {material}: the cache has no material paths; re-bake it with this version")
    ids = [index for index, path in enumerate(material_paths) if path == material]
    if not ids:
        known = ", ".join(sorted(set(material_paths))[:8])
        raise RelightError(
            f"no material {material} in the cache (its materials: {known}{', ...' * (len(set(material_paths)) > 8)})"
        )
    return torch.isin(material_ids, torch.tensor(ids, dtype=material_ids.dtype, device=material_ids.device))


def apply_material_edit(
    params: PreviewSurfaceParams,
    material_ids: torch.Tensor,
    material: int | str,
    values: Mapping[str, object],
    material_paths: list[str] | None = None,
) -> tuple[PreviewSurfaceParams, torch.Tensor]:
    """`params` with `values` (input name -> constant: 3 numbers for a colour, or one for grey; one
    number otherwise) set on the rows of `material` (`material_rows`; `material_ids` (N,)), and
    those rows ((N,) bool).

    Raises:
        RelightError: an unknown material, an input that is not a `PreviewSurfaceParams` field, a
            refused one, or a value of the wrong shape, naming the input and the material.
    """
    if not values:
        raise RelightError(f"material {material}: no input to edit")
    rows = material_rows(material_ids, material, material_paths)
    changes = {}
    for name, value in values.items():
        if name in REFUSED_INPUTS:
            raise RelightError(f"material {material}: {name}: {REFUSED_INPUTS[name]}")
        field = getattr(params, name, None)
        if not isinstance(field, torch.Tensor):
            inputs = ", ".join(f.name for f in dataclasses.fields(params) if f.name not in REFUSED_INPUTS)
            raise RelightError(f"material {material}: no input {name!r} (UsdPreviewSurface inputs: {inputs})")
        try:
            new = torch.as_tensor(value, dtype=field.dtype, device=field.device)
            new = new.expand(field.shape[1:]).expand_as(field) if field.dim() > 1 else new.expand_as(field)
        except (RuntimeError, TypeError, ValueError):
            shape = f"{field.shape[1]} numbers" if field.dim() > 1 else "one number"
            raise RelightError(f"material {material}: {name} takes {shape}, got {value!r}") from None
        mask = rows.reshape(-1, *([1] * (field.dim() - 1)))
        changes[name] = torch.where(mask, new, field)
    return dataclasses.replace(params, **changes), rows


def layer_material_edits(
    description: CacheDescription, layer: str | os.PathLike[str], material_paths: list[str] | None
) -> dict[str, dict[str, object]]:
    """The material edits a USD layer authors: material prim path -> {`PreviewSurfaceParams` field:
    constant}. The layer is composed over the cache's shot as its strongest sublayer, and each
    material's UsdPreviewSurface input takes the value a renderer would (through a connection to
    the material's interface input, at the baked time); an input is edited where the attribute
    giving its value has an opinion in the layer.

    Inputs of other prims (a light's, when one layer holds both kinds of edits) are left to
    their readers.

    Raises:
        RelightError: the layer is missing or not USD; the cache has no material paths; an
            `inputs:` attribute on or beneath a material, or on a prim defined nowhere, that gives
            no UsdPreviewSurface input of the cache's materials its value (naming it), or one
            overridden by a connection.
    """
    if material_paths is None:
        raise RelightError(f"materials layer {layer}: the cache has no material paths; re-bake it with this version")
    stage = open_stage(description.source, materials_layer=layer)
    edits_layer = open_layer(layer, "materials layer")
    authored: set[Sdf.Path] = set()
    edits_layer.Traverse(
        Sdf.Path.absoluteRootPath,
        lambda path: authored.add(path) if path.IsPropertyPath() and path.name.startswith("inputs:") else None,
    )
    time = description.parameters.get("time")
    at = time_code(stage, None if time is None else float(time))  # as the bake read the materials
    edits: dict[str, dict[str, object]] = {}
    used: set[Sdf.Path] = set()
    for material_path in prim_material_paths(material_paths):
        shader = _preview_surface(stage, material_path)
        if shader is None:
            continue
        for name, field in USD_INPUT_FIELDS.items():
            shader_input = shader.GetInput(name)
            if not shader_input:
                continue
            sources = [attribute.GetPath() for attribute in shader_input.GetValueProducingAttributes()]
            own = shader_input.GetAttr().GetPath()
            if own in authored and own not in sources:
                raise RelightError(
                    f"materials layer {layer}: {own}: connected to {sources[0] if sources else 'nothing'}, "
                    "so its value is not used; set the input it is connected to"
                )
            for source in sources:
                if source in authored:
                    if UsdShade.Output.IsOutput(stage.GetAttributeAtPath(source)):
                        raise RelightError(f"materials layer {layer}: {source}: a shader output, not a constant")
                    value = stage.GetAttributeAtPath(source).Get(at)
                    edits.setdefault(material_path, {})[field] = _constant(value, f"materials layer {layer}: {source}")
                    used.add(source)
    unused = sorted((path for path in authored - used if _in_material_or_undefined(stage, path)), key=str)
    if unused:
        raise RelightError(
            f"materials layer {layer}: {unused[0]}: gives no UsdPreviewSurface input of the cache's materials its "
            f"value ({', '.join(USD_INPUT_FIELDS)})"
        )
    return edits


def relighter_layer_edits(
    relighter: CacheRelighter, description: CacheDescription, layer: str | os.PathLike[str]
) -> dict[str, dict[str, object]]:
    """The material edits `layer` authors (`layer_material_edits`) for the relighter of the cache
    `description` records.

    Raises:
        RelightError: the relighter has no material edits (naming the cache's method), or as
            `layer_material_edits`.
    """
    if not relighter.material_edits:
        raise RelightError(
            f"a {description.method!r} cache's light transport holds its materials; bake it with --method direct "
            "or --method cuts to edit materials"
        )
    return layer_material_edits(description, layer, relighter.material_paths)


def write_material_edits(
    layer: Sdf.Layer, description: CacheDescription, edits: Mapping[str, Mapping[str, object]]
) -> None:
    """Author `edits` (material prim path -> {`PreviewSurfaceParams` field: constant}) into `layer`
    as `layer_material_edits` reads them: on the attribute that gives each UsdPreviewSurface input
    its value in the cache's shot (the input itself, or the material's interface input it is
    connected to)."""
    stage = open_stage(description.source)
    names = {field: name for name, field in USD_INPUT_FIELDS.items()}
    for material_path, values in sorted(edits.items()):
        shader = _preview_surface(stage, material_path)
        if shader is None:
            raise RelightError(f"{material_path}: no UsdPreviewSurface shader to write its edits on")
        for field, value in sorted(values.items()):
            name = names[field]
            shader_input = shader.GetInput(name)
            sources = shader_input.GetValueProducingAttributes() if shader_input else []
            target = sources[0].GetPath() if sources else shader.GetPath().AppendProperty(f"inputs:{name}")
            spec = Sdf.CreatePrimInLayer(layer, target.GetPrimPath())  # an `over` where the layer has none
            attribute = layer.GetAttributeAtPath(target) or Sdf.AttributeSpec(spec, target.name, _value_type(value))
            attribute.default = _usd_value(value)


def _preview_surface(stage: Usd.Stage, material_path: str) -> UsdShade.Shader | None:
    """The UsdPreviewSurface shader of the material at `material_path`'s universal surface, or
    None (another shader, or none)."""
    shader = UsdShade.Material(stage.GetPrimAtPath(material_path)).ComputeSurfaceSource()[0]
    return shader if shader and shader.GetShaderId() == "UsdPreviewSurface" else None


def _value_type(value: object) -> Sdf.ValueTypeName:
    """The UsdPreviewSurface type of an input's constant: color3f, int (the workflow) or float."""
    if isinstance(value, tuple):
        return Sdf.ValueTypeNames.Color3f
    return Sdf.ValueTypeNames.Int if isinstance(value, bool) else Sdf.ValueTypeNames.Float


def _usd_value(value: object) -> object:
    """A constant as USD stores it (`_value_type`)."""
    if isinstance(value, tuple):
        return Gf.Vec3f(*value)
    return int(value) if isinstance(value, bool) else value


def apply_materials_layer(
    relighter: CacheRelighter, description: CacheDescription, layer: str | os.PathLike[str]
) -> None:
    """Make the material edits `layer` authors on the relighter (`relighter_layer_edits`).

    Raises:
        RelightError: as `relighter_layer_edits` and `CacheRelighter.edit_material`.
    """
    for material, values in relighter_layer_edits(relighter, description, layer).items():
        relighter.edit_material(material, **values)


def _in_material_or_undefined(stage: Usd.Stage, attribute: Sdf.Path) -> bool:
    """Whether an attribute's prim is a material, lies beneath one, or is defined nowhere but in
    an `over` (a misspelt path): an input the materials layer should have given a value to. Other
    prims' inputs (a light's, from the same layer) are not its business."""
    prim = stage.GetPrimAtPath(attribute.GetPrimPath())
    if not prim or not prim.IsDefined():
        return True
    while prim and not prim.IsPseudoRoot():
        if prim.IsA(UsdShade.Material):
            return True
        prim = prim.GetParent()
    return False


def _constant(value: object, where: str) -> object:
    """A USD input value as `apply_material_edit` takes it: the number, or a tuple for a colour.

    Raises:
        RelightError: neither (`where` names the attribute).
    """
    if isinstance(value, bool | int | float):
        return value
    try:
        return tuple(float(v) for v in value)  # type: ignore[attr-defined]  # Gf.Vec3f iterates
    except (TypeError, ValueError):
        raise RelightError(f"{where}: {value!r} is neither a number nor a colour") from None
