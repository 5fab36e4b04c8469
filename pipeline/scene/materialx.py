"""MaterialX surfaces mapped onto the shared UsdPreviewSurface BRDF (docs/MATERIALS.md).

Three surface nodes are read, wherever they are authored (a UsdShade network whose surface shader
has `info:id` ND_standard_surface_surfaceshader, ND_open_pbr_surface_surfaceshader or
ND_UsdPreviewSurface_surfaceshader, or a `.mtlx` document a USD material references):

* `UsdPreviewSurface`: input for input, exact.
* `standard_surface`: MaterialX's own translation graph (`ND_standard_surface_to_UsdPreviewSurface`,
  libraries/bxdf/translation/standard_surface_to_usd.mtlx), written out here:
  diffuseColor = mix(subsurface_color, base * base_color, subsurface) * mix(1, coat_color, coat),
  metallic = metalness, roughness = specular_roughness, ior = specular_IOR,
  clearcoat = coat * mean(coat_color), clearcoatRoughness = coat_roughness,
  emissiveColor = emission * emission_color * mix(1, coat_color, coat), opacity = mean(opacity),
  normal = the tangent-space value of a `normalmap` node.
* `open_pbr_surface`: MaterialX's OpenPBR -> Standard Surface translation composed with the one
  above (base_weight, base_metalness, specular_ior, coat_weight, emission_luminance,
  geometry_opacity, geometry_normal under their Standard Surface names); coat darkening is
  not modelled.

What UsdPreviewSurface cannot express (transmission, sheen / fuzz, thin film, anisotropy, diffuse
roughness, a dielectric specular weight or tint, a separate coat IOR, thin walls) is dropped with
one warning per material naming the inputs.

`.mtlx` documents are read with the `materialx` package: usd-core's wheel has no MaterialX file
format plugin, so USD cannot compose them (`relight_torch.stage.composition_problems` keeps that
from failing the stage).
"""

from __future__ import annotations

import os
from collections.abc import Callable

import MaterialX as mx
import numpy as np
from pxr import Sdf, Usd, UsdShade

from pipeline.errors import RelightError
from pipeline.scene.materialx_graph import (
    GraphEvaluator,
    MtlxNode,
    Node,
    UsdNode,
    as_floats,
    channel_mean,
    fit_input,
    standard_library,
)
from pipeline.scene.textures import ImageCache
from pipeline.scene.types import Material, MaterialInput

SURFACE_NODEDEFS = {
    "standard_surface": "ND_standard_surface_surfaceshader",
    "open_pbr_surface": "ND_open_pbr_surface_surfaceshader",
    "UsdPreviewSurface": "ND_UsdPreviewSurface_surfaceshader",
}
SURFACE_IDS = frozenset(SURFACE_NODEDEFS.values())
"""UsdShade `info:id`s of the MaterialX surfaces this module maps."""

# Inputs UsdPreviewSurface cannot express: (name, value at which it has no effect).
_STANDARD_SURFACE_DROPPED = (
    ("transmission", 0.0),
    ("sheen", 0.0),
    ("thin_film_thickness", 0.0),
    ("specular_anisotropy", 0.0),
    ("coat_anisotropy", 0.0),
    ("diffuse_roughness", 0.0),
    ("coat_affect_color", 0.0),
    ("coat_affect_roughness", 0.0),
    ("thin_walled", False),
)
_OPEN_PBR_DROPPED = (
    ("transmission_weight", 0.0),
    ("fuzz_weight", 0.0),
    ("thin_film_weight", 0.0),
    ("specular_roughness_anisotropy", 0.0),
    ("coat_roughness_anisotropy", 0.0),
    ("base_diffuse_roughness", 0.0),
    ("geometry_thin_walled", False),
)
# Standard Surface input names of the OpenPBR inputs the mapping uses (MaterialX's translation graph).
_OPEN_PBR_NAMES = {
    "base": "base_weight",
    "base_color": "base_color",
    "metalness": "base_metalness",
    "specular": "specular_weight",
    "specular_color": "specular_color",
    "specular_roughness": "specular_roughness",
    "specular_IOR": "specular_ior",
    "subsurface": "subsurface_weight",
    "subsurface_color": "subsurface_color",
    "coat": "coat_weight",
    "coat_color": "coat_color",
    "coat_roughness": "coat_roughness",
    "coat_IOR": "coat_ior",
    "emission": "emission_luminance",
    "emission_color": "emission_color",
    "opacity": "geometry_opacity",
    "normal": "geometry_normal",
}
_STANDARD_SURFACE_NAMES = {name: name for name in _OPEN_PBR_NAMES}
_PREVIEW_INPUTS = {
    "diffuseColor": ("diffuse_color", 3),
    "emissiveColor": ("emissive_color", 3),
    "specularColor": ("specular_color", 3),
    "metallic": ("metallic", 1),
    "roughness": ("roughness", 1),
    "clearcoat": ("clearcoat", 1),
    "clearcoatRoughness": ("clearcoat_roughness", 1),
    "opacity": ("opacity", 1),
    "ior": ("ior", 1),
    "normal": ("normal", 3),
}
_OPACITY_MODES = {0: "transparent", 1: "presence", "transparent": "transparent", "presence": "presence"}
_NEUTRAL_NORMAL = np.array([0.0, 0.0, 1.0], np.float32)


class _Surface:
    """A surface node's inputs, evaluated on demand with the nodedef's defaults."""

    def __init__(self, node: Node, evaluator: GraphEvaluator):
        self.node = node
        self.evaluator = evaluator
        self._nodedef = standard_library().getNodeDef(SURFACE_NODEDEFS[node.category])

    def default(self, name: str, num_channels: int) -> np.ndarray:
        nodedef_input = self._nodedef.getActiveInput(name)
        if nodedef_input is None or not nodedef_input.getValueString():
            return np.zeros(num_channels, np.float32)
        return as_floats(_floats(nodedef_input.getValue()), num_channels)

    def input(self, name: str, num_channels: int) -> MaterialInput:
        return self.evaluator.evaluate(self.node.port(name), self.default(name, num_channels), name)

    def constant(self, name: str):
        """The input's value when it is not connected, else None."""
        port = self.node.port(name)
        return None if port is None or port.node is not None else port.value

    def is_used(self, name: str, neutral) -> bool:
        """Whether an input has an effect: connected, or a constant other than `neutral`."""
        port = self.node.port(name)
        if port is None:
            return False
        if port.node is not None:
            return True
        if port.value is None or isinstance(neutral, bool):
            return port.value is not None and bool(port.value) != neutral
        return bool(np.any(np.asarray(port.value, np.float32) != neutral))


def _floats(value):
    return value.asTuple() if hasattr(value, "asTuple") else value


def _normal(surface: _Surface, name: str) -> MaterialInput:
    """A Standard Surface / OpenPBR `normal` (world space) as a tangent-space normal: only the
    output of a `normalmap` node has one; anything else is the unperturbed normal."""
    port = surface.node.port(name)
    if port is None or port.node is None:
        return MaterialInput(_NEUTRAL_NORMAL)
    if port.node.category != "normalmap":
        surface.evaluator.warn(
            f"{name} comes from {port.node.name} ('{port.node.category}'), not a normalmap "
            f"node; using the unperturbed normal"
        )
        return MaterialInput(_NEUTRAL_NORMAL)
    return surface.evaluator.evaluate(port, _NEUTRAL_NORMAL, name)


def _standard_surface_fields(surface: _Surface, names: dict[str, str]) -> dict:
    """Material fields of a standard_surface (names: identity) or open_pbr_surface (names: the
    OpenPBR inputs under their Standard Surface names)."""
    evaluator = surface.evaluator

    def get(name: str, num_channels: int) -> MaterialInput:
        return surface.input(names[name], num_channels)

    coat = get("coat", 1)
    coat_color = get("coat_color", 3)
    coat_tint = evaluator.mix(coat_color, MaterialInput(np.ones(3, np.float32)), fit_input(coat, 1), "coat_color")
    base_color = evaluator.product(get("base_color", 3), fit_input(get("base", 1), 3), "base_color")
    albedo = evaluator.mix(get("subsurface_color", 3), base_color, get("subsurface", 1), "subsurface_color")
    emission = evaluator.product(get("emission_color", 3), fit_input(get("emission", 1), 3), "emission_color")
    opacity = get("opacity", 3)
    return {
        "diffuse_color": evaluator.product(albedo, coat_tint, "base_color"),
        "metallic": get("metalness", 1),
        "roughness": get("specular_roughness", 1),
        "ior": get("specular_IOR", 1),
        "clearcoat": channel_mean(evaluator.product(coat_color, fit_input(coat, 3), "coat")),
        "clearcoat_roughness": get("coat_roughness", 1),
        "emissive_color": evaluator.product(emission, coat_tint, "emission_color"),
        "opacity": channel_mean(opacity) if opacity.value.size == 3 else opacity,
        "normal": _normal(surface, names["normal"]),
    }


def _dropped(surface: _Surface, names: dict[str, str], dropped: tuple) -> list[str]:
    """The inputs in use that the mapping drops or approximates, for the warning."""
    unused = [name for name, neutral in dropped if surface.is_used(name, neutral)]
    metalness = surface.constant(names["metalness"])
    dielectric = metalness is None or float(np.asarray(metalness).reshape(-1)[0]) < 1.0
    if dielectric and (surface.is_used(names["specular"], 1.0) or surface.is_used(names["specular_color"], 1.0)):
        unused.append(f"{names['specular']}/{names['specular_color']} (dielectric F0 comes from the IOR alone)")
    if surface.is_used(names["subsurface"], 0.0):
        unused.append(f"{names['subsurface']} (its colour is mixed into the diffuse colour)")
    coat_ior = surface.constant(names["coat_IOR"])
    specular_ior = surface.constant(names["specular_IOR"])
    if surface.is_used(names["coat"], 0.0) and (
        coat_ior is None or specular_ior is None or not np.allclose(coat_ior, specular_ior)
    ):
        unused.append(f"{names['coat_IOR']} (the coat reflects with the base IOR)")
    return unused


def _preview_surface_fields(surface: _Surface) -> dict:
    """Material fields of a MaterialX UsdPreviewSurface: input for input."""
    fields = {field: surface.input(name, num_channels) for name, (field, num_channels) in _PREVIEW_INPUTS.items()}
    use_specular = surface.constant("useSpecularWorkflow")
    threshold = surface.constant("opacityThreshold")
    mode = surface.constant("opacityMode")
    fields["use_specular_workflow"] = bool(use_specular) if use_specular is not None else False
    fields["opacity_threshold"] = float(np.asarray(threshold).reshape(-1)[0]) if threshold is not None else 0.0
    if mode is not None:
        key = mode if isinstance(mode, str) else int(np.asarray(mode).reshape(-1)[0])
        if key not in _OPACITY_MODES:
            surface.evaluator.warn(f"unknown opacityMode '{mode}'; using 'transparent'")
        fields["opacity_mode"] = _OPACITY_MODES.get(key, "transparent")
    return fields


def surface_material(
    path: str, node: Node, images: ImageCache, warn: Callable[[str], None], documents: tuple[str, ...] = ()
) -> Material:
    """Map a MaterialX surface node onto a `Material`.

    Args:
        path: the material prim's path (the record's path, named in warnings).
        node: a standard_surface, open_pbr_surface or UsdPreviewSurface node.
        images: the library's image cache.
        warn: one-line warning sink.
        documents: `.mtlx` files the material was read from (bake inputs).

    Raises:
        RelightError: a non-finite input value.
    """
    evaluator = GraphEvaluator(path, images, warn)
    surface = _Surface(node, evaluator)
    try:
        if node.category == "UsdPreviewSurface":
            fields = _preview_surface_fields(surface)
        else:
            if node.category == "standard_surface":
                names, dropped = _STANDARD_SURFACE_NAMES, _STANDARD_SURFACE_DROPPED
            else:
                names, dropped = _OPEN_PBR_NAMES, _OPEN_PBR_DROPPED
            fields = _standard_surface_fields(surface, names)
            unused = _dropped(surface, names, dropped)
            if unused:
                evaluator.warn(
                    f"{node.category} {node.name}: not representable in UsdPreviewSurface, dropped or "
                    f"approximated: {', '.join(unused)} (docs/MATERIALS.md)"
                )
    except RelightError as error:
        raise RelightError(f"material {path}: {node.name}: {error}") from None
    return Material(path, documents=documents, **fields)


def usd_surface_material(
    path: str, shader: UsdShade.Shader, time: Usd.TimeCode, images: ImageCache, warn: Callable[[str], None]
) -> Material:
    """`surface_material` of a UsdShade shader whose id is in `SURFACE_IDS`."""
    return surface_material(path, UsdNode(shader, time), images, warn)


# .mtlx documents referenced from USD ----------------------------------------------------------


def mtlx_references(prim: Usd.Prim) -> list[tuple[str, str]]:
    """The `.mtlx` documents a prim's composed specs reference: [(absolute file, target prim path)],
    strongest first (selected variants included: they are in the prim stack)."""
    found = []
    for spec in prim.GetPrimStack():
        arcs = list(spec.referenceList.GetAddedOrExplicitItems()) + list(spec.payloadList.GetAddedOrExplicitItems())
        for arc in arcs:
            if arc.assetPath.lower().endswith(".mtlx"):
                found.append((spec.layer.ComputeAbsolutePath(arc.assetPath), str(arc.primPath)))
    return found


def _read_document(file: str) -> mx.Document:
    if not os.path.isfile(file):
        raise RelightError(f"MaterialX document {file} not found")
    document = mx.createDocument()
    try:
        mx.readFromXmlFile(document, file, mx.FileSearchPath(os.path.dirname(file)))
    except (mx.ExceptionParseError, mx.ExceptionFileMissing) as error:  # an XInclude may be missing too
        raise RelightError(f"MaterialX document {file} is not readable: {str(error).splitlines()[0]}") from None
    document.setDataLibrary(standard_library())
    return document


def _material_node(document: mx.Document, file: str, target: str, prim_name: str) -> mx.Node:
    """The surfacematerial a reference targets: usdMtlx names it /MaterialX/Materials/<name>;
    without a target, the material named like the prim, else the document's only one."""
    materials = {node.getName(): node for node in document.getMaterialNodes()}
    name = Sdf.Path(target).name if target and Sdf.Path(target).pathElementCount > 1 else ""
    for candidate in (name, prim_name):
        if candidate in materials:
            return materials[candidate]
    if not name and len(materials) == 1:
        return next(iter(materials.values()))
    raise RelightError(
        f"MaterialX document {file} has no material '{name or prim_name}' "
        f"(it has: {', '.join(sorted(materials)) or 'none'})"
    )


def document_material(
    path: str, prim_name: str, file: str, target: str, images: ImageCache, warn: Callable[[str], None]
) -> Material:
    """The `Material` of a USD material prim that references `target` in the `.mtlx` document `file`.

    Raises:
        RelightError: the document is missing or unreadable, has no such material, or its surface is
            not one of the mapped nodes (the caller warns and falls back to grey).
    """
    document = _read_document(file)
    material = _material_node(document, file, target, prim_name)
    shader_input = material.getInput("surfaceshader")
    shader = shader_input.getConnectedNode() if shader_input is not None else None
    if shader is None:
        raise RelightError(f"MaterialX material {material.getName()} in {file} has no surfaceshader")
    if shader.getCategory() not in SURFACE_NODEDEFS:
        raise RelightError(
            f"MaterialX material {material.getName()} in {file}: surface '{shader.getCategory()}' "
            f"is not one of {', '.join(SURFACE_NODEDEFS)}"
        )
    return surface_material(path, MtlxNode(shader, os.path.dirname(file)), images, warn, documents=(file,))
