"""Opening a shot, optionally with a layer of light edits composed over it.

The light edits (`relight ... --lights LAYER`) go in as the STRONGEST sublayer of an anonymous root
layer whose weaker sublayer is the shot, so an edit overrides the shot's opinion on any light
attribute and may also define new lights. Stage metadata is read from the root layer only, so the
anonymous root copies the shot's (up axis, units, time codes, default prim, render settings).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

from pxr import Sdf, Tf, Usd, UsdShade

from relight_torch.errors import RelightError
from relight_torch.schema import register_schemas

# Root-layer metadata that must come from the shot: geometry units and axes, and the time-code
# rate (a sublayer whose rate differs from its root's is rescaled in time).
_SHOT_METADATA = (
    "upAxis",
    "metersPerUnit",
    "defaultPrim",
    "timeCodesPerSecond",
    "framesPerSecond",
    "startTimeCode",
    "endTimeCode",
    "renderSettingsPrimPath",
)


def usd_error_line(error: Exception) -> str:
    """The first non-empty line of a (possibly multi-line) pxr error message.

    pxr cannot even build the message of some errors on a file that is not UTF-8 (its `str()`
    raises UnicodeDecodeError, as does `.args`): those say so.
    """
    try:
        text = str(error)
    except UnicodeDecodeError:
        return "it holds bytes that are not UTF-8 text"
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return lines[0] if lines else type(error).__name__


def open_layer(path: str | os.PathLike[str], role: str) -> Sdf.Layer:
    """Open `path` as an Sdf layer, raising `RelightError` if it is missing or not USD.

    Args:
        path: file path of a .usd/.usda/.usdc/.usdz file.
        role: what the file is for ("stage", "lights layer"), used in messages.
    """
    file = Path(path)
    if not file.is_file():
        raise RelightError(f"{role} not found: {file}")
    try:
        layer = Sdf.Layer.FindOrOpen(str(file.resolve()))
    except Tf.ErrorException as error:
        raise RelightError(f"{role} {file} is not a readable USD file: {usd_error_line(error)}") from None
    if layer is None:
        raise RelightError(f"{role} {file} is not a readable USD file")
    return layer


def open_stage(
    path: str | os.PathLike[str],
    lights_layer: str | os.PathLike[str] | None = None,
    materials_layer: str | os.PathLike[str] | None = None,
) -> Usd.Stage:
    """Open a shot (.usd, .usda, .usdc or .usdz), with optional layers of edits over it.

    Registers the project's schemas first (they must be known before any stage is opened).

    Args:
        path: the shot's root layer.
        lights_layer: a USD layer of light edits, composed as the strongest sublayer over the
            shot; None: none.
        materials_layer: a USD layer of material edits (`relight_torch.material_edits`),
            composed over the shot below the lights layer; None: none.

    Returns:
        The composed stage, payloads loaded.

    Raises:
        RelightError: a file is missing, is not USD, or the stage cannot be composed.
    """
    register_schemas()
    shot = open_layer(path, "stage")
    root = shot
    edits = [(lights_layer, "lights layer"), (materials_layer, "materials layer")]
    layers = [open_layer(layer, role) for layer, role in edits if layer is not None]
    if layers:
        root = Sdf.Layer.CreateAnonymous("relight_root.usda")
        for layer in [*layers, shot]:
            root.subLayerPaths.append(layer.identifier)
        for key in _SHOT_METADATA:
            if shot.pseudoRoot.HasInfo(key):
                root.pseudoRoot.SetInfo(key, shot.pseudoRoot.GetInfo(key))
    try:
        return Usd.Stage.Open(root, Usd.Stage.LoadAll)
    except Tf.ErrorException as error:
        raise RelightError(f"stage {path} could not be opened: {usd_error_line(error)}") from None


def time_code(stage: Usd.Stage, time: float | None) -> Usd.TimeCode:
    """The time code to read: `time`, else the stage's first frame.

    The first frame is the authored startTimeCode, else the earliest time sample (attributes
    without samples read their default value either way). Not `Usd.TimeCode.Default()`: that
    reads nothing from attributes that only have time samples, e.g. animated points.
    """
    if time is not None:
        return Usd.TimeCode(time)
    if stage.HasAuthoredTimeCodeRange():
        return Usd.TimeCode(stage.GetStartTimeCode())
    return Usd.TimeCode.EarliestTime()


MISSING_FILE_ERRORS = ("ErrorInvalidSublayerPath", "ErrorInvalidAssetPath", "ErrorInvalidExternalTargetPath")
"""Composition errors that mean a file the shot names is missing or unreadable."""

_ASSET_IN_MESSAGE = re.compile(r"@([^@]+)@")


@dataclass(frozen=True)
class CompositionProblems:
    """The missing-file composition errors of a stage, sorted by what they can cost.

    Attributes:
        fatal: one line per error that may lose geometry, lights or cameras (a sublayer, or a
            reference or payload on any prim that is not part of a material): USD composes the
            stage without the file, so the bake would silently miss what it holds.
        material: (prim path, asset, one-line message) per error on a UsdShade Material, Shader or
            NodeGraph prim or below a Material, or naming a MaterialX document (.mtlx, which
            usd-core's wheel cannot read): only that material's look is lost, and the material
            reader falls back as docs/MATERIALS.md documents.
    """

    fatal: tuple[str, ...]
    material: tuple[tuple[str, str, str], ...]


def _first_line(error: object) -> str:
    return str(error).strip().splitlines()[0].removesuffix("; skipping.")


def _is_material_site(stage: Usd.Stage, path: Sdf.Path) -> bool:
    """Whether the prim at `path` is a shading prim or inside a Material."""
    prim = stage.GetPrimAtPath(path)
    while prim and not prim.IsPseudoRoot():
        if prim.IsA(UsdShade.Material) or prim.IsA(UsdShade.Shader) or prim.IsA(UsdShade.NodeGraph):
            return True
        prim = prim.GetParent()
    return False


def composition_problems(stage: Usd.Stage) -> CompositionProblems:
    """Sort a stage's missing-file composition errors into fatal ones and material ones.

    A reference is a material asset when its prim is a shading prim or lies inside a Material, or
    when the asset is a `.mtlx` document (whatever the prim's type: a MaterialX reference is how
    a look is brought in). Everything else, a sublayer above all, stays fatal.
    """
    fatal, material = [], []
    for error in stage.GetCompositionErrors():
        if type(error).__name__ not in MISSING_FILE_ERRORS:
            continue
        message = _first_line(error)
        asset_match = _ASSET_IN_MESSAGE.search(message)
        asset = asset_match.group(1) if asset_match else ""
        site = getattr(error, "rootSite", None)
        path = site.path if site is not None and type(error).__name__ != "ErrorInvalidSublayerPath" else None
        if path is not None and (asset.lower().endswith(".mtlx") or _is_material_site(stage, path)):
            material.append((str(path), asset, message))
        else:
            fatal.append(message)
    return CompositionProblems(tuple(fatal), tuple(material))


def defining_layer(stage: Usd.Stage, message: str, shot: str | Path) -> str:
    """The file of the strongest layer authoring the prim a walker message starts with ('/Rig/Key: ...'),
    else the shot: the walker names prims, the user needs the file to fix too."""
    prim_path = message.split(":", 1)[0]
    prim = stage.GetPrimAtPath(prim_path) if Sdf.Path.IsValidPathString(prim_path) else None
    stack = prim.GetPrimStack() if prim else []
    return next((spec.layer.realPath for spec in stack if spec.layer.realPath), str(shot))


def check_composition(stage: Usd.Stage, path: str | Path) -> list[str]:
    """Refuse a stage that names a missing or unreadable file, unless only a material's look is lost.

    A sublayer, or a reference or payload of geometry, lights or cameras, is fatal (USD would compose
    the stage without it). One that concerns only a material (`relight_torch.stage.composition_problems`)
    is a warning: the material reader reads `.mtlx` documents itself and falls back as documented
    in docs/MATERIALS.md.

    Returns:
        One warning per material problem that the material reader does not handle itself (a
        `.mtlx` reference is reported there, once it is known whether the document reads).

    Raises:
        RelightError: one line naming the shot, the layer and the file, and how many more there are.
    """
    problems = composition_problems(stage)
    if problems.fatal:
        more = f" (and {len(problems.fatal) - 1} more)" if len(problems.fatal) > 1 else ""
        raise RelightError(f"stage {path}: {problems.fatal[0]}{more}")
    return [
        f"stage {path}: material {prim}: {message}; rendering the material without it (grey 0.18 diffuse "
        f"if no surface shader is left, docs/MATERIALS.md)"
        for prim, asset, message in problems.material
        if not asset.lower().endswith(".mtlx")
    ]


def outside_reads(shot: str | os.PathLike[str], lights_layer: str | os.PathLike[str]) -> list[str]:
    """Files a lights layer names outside the shot's and the lights layer's folders, one line each.

    Walks the lights layer and every layer it brings in (sublayers, references, payloads) and
    lists each of those arcs and each asset-valued attribute (textures, cookies, IES profiles...)
    whose file lies outside both folders (and their subfolders): a lights layer handed over with a
    shot should not make the relighter read files elsewhere without a word. Missing files are not
    reported here (`check_composition` and the light reader refuse them).

    Returns:
        '<layer>: <prim>: <what> names <file>, outside the shot's folder <dir> and the lights
        layer's folder <dir>; read all the same' lines, in the order found.
    """
    roots = [Path(shot).resolve().parent, Path(lights_layer).resolve().parent]
    lines: list[str] = []
    seen: set[str] = set()
    pending = [str(Path(lights_layer).resolve())]
    while pending:
        file = pending.pop(0)
        if file in seen:
            continue
        seen.add(file)
        try:
            layer = Sdf.Layer.FindOrOpen(file)
        except Tf.ErrorException:
            layer = None
        if layer is None:
            continue
        for where, asset, arc in _named_files(layer):
            resolved = Path(layer.ComputeAbsolutePath(asset)).resolve()
            if not any(resolved.is_relative_to(root) for root in roots):
                lines.append(
                    f"{layer.realPath}: {where} names {resolved}, outside the shot's folder {roots[0]} and the "
                    f"lights layer's folder {roots[1]}; read all the same"
                )
            if arc:
                pending.append(str(resolved))
    return lines


def _named_files(layer: Sdf.Layer) -> list[tuple[str, str, bool]]:
    """(where, authored asset path, is a composition arc) of every file `layer` names."""
    named: list[tuple[str, str, bool]] = [("subLayers", path, True) for path in layer.subLayerPaths if path]

    def visit(path: Sdf.Path) -> None:
        if path.IsPrimPath():
            spec = layer.GetPrimAtPath(path)
            for kind, items in (("references", spec.referenceList), ("payload", spec.payloadList)):
                for item in {*items.explicitItems, *items.prependedItems, *items.appendedItems, *items.addedItems}:
                    if item.assetPath:
                        named.append((f"{path}: {kind}", item.assetPath, True))
        elif path.IsPropertyPath():
            spec = layer.GetAttributeAtPath(path)
            if spec is None or spec.typeName not in (Sdf.ValueTypeNames.Asset, Sdf.ValueTypeNames.AssetArray):
                return
            values = [spec.default] + [layer.QueryTimeSample(path, t) for t in layer.ListTimeSamplesForPath(path)]
            for value in values:
                for asset in value if isinstance(value, (list, tuple, Sdf.AssetPathArray)) else [value]:
                    if isinstance(asset, Sdf.AssetPath) and asset.path:
                        named.append((f"{path.GetPrimPath()}: {path.name}", asset.path, False))

    layer.Traverse(Sdf.Path.absoluteRootPath, visit)
    return named
