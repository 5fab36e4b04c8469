"""Read bound UsdShade materials into `Material` records (UsdPreviewSurface + UsdUVTexture).

`MaterialLibrary` turns the material a gprim is bound to into an index into `Scene.materials`,
reading each material prim once. The surface shader comes from `ComputeSurfaceSource()` (the
universal render context) and every input through `GetValueProducingAttributes()`, which follows
NodeGraph outputs and Material / NodeGraph interface inputs. Supported nodes feeding an input:

* `UsdUVTexture` (file, st, wrapS/T, scale, bias, fallback, sourceColorSpace; outputs rgb/r/g/b/a),
  its st from `UsdPrimvarReader_float2`, possibly through chained `UsdTransform2d`;
* `UsdPrimvarReader_*` of `displayColor`: the gprim's constant displayColor, so such materials get
  one entry per distinct colour.

Anything else (another shader id, a reader of another primvar) is warned about once per material and
replaced by the input's constant. Values are read at `time` (default: the default time code).

MaterialX surfaces (`pipeline.scene.materialx`) are read too: a surface shader with a MaterialX id
(universal render context first, then 'mtlx'), and a material prim that references a `.mtlx`
document (which usd-core cannot compose: the document is read with the `materialx` package).
A material that cannot be read this way warns and renders as the grey fallback.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
from pxr import Sdf, Usd, UsdShade

from pipeline.errors import RelightError, warn
from pipeline.scene import materialx
from pipeline.scene.textures import ImageCache, fit_channels, load_texture, select_output
from pipeline.scene.types import Material, MaterialInput
from relight_torch.brdf.preview_surface import USD_INPUT_FIELDS

# UsdPreviewSurface inputs that may be textured -> Material field.
_TEXTURABLE_INPUTS = {name: field for name, field in USD_INPUT_FIELDS.items() if name != "useSpecularWorkflow"} | {
    "normal": "normal"
}
_OPACITY_MODES = ("transparent", "presence")
_DISPLAY_COLOR = "displayColor"
# Materials the library synthesises for gprims without a (usable) binding.
DISPLAY_COLOR_PATH = "<displayColor>"
FALLBACK_PATH = "<fallback>"
_MAX_NODE_DEPTH = 64


@dataclass(frozen=True)
class _ParsedMaterial:
    """A material prim read once: its record, and the fields fed by a displayColor primvar reader."""

    material: Material
    display_color_fields: tuple[str, ...]


def _is_output(attribute: Usd.Attribute) -> bool:
    return UsdShade.Utils.GetType(attribute.GetName()) == UsdShade.AttributeType.Output


def _as_array(value, attribute: Usd.Attribute) -> np.ndarray:
    """A USD value (float, Gf vector) as a (C,) float32 array; non-finite values are an input error."""
    array = np.atleast_1d(np.asarray(value, np.float32)).reshape(-1)
    if not np.all(np.isfinite(array)):
        raise RelightError(f"{attribute.GetPath()}: non-finite value {value}")
    return array


class MaterialLibrary:
    """Materials of one stage, in first-use order; `id_for` gives a gprim's material index.

    Args:
        stage: the composed stage the materials come from (materials are read through the prims
            handed to `id_for`, which carry it; asset paths resolve in its resolver context).
        warnings: the scene's warning list (`pipeline.errors.warn` sink).
        time: time code for input values (`Usd.TimeCode.Default()` unless the walker passes the
            shot time).
    """

    def __init__(self, stage: Usd.Stage, warnings: list[str], time: Usd.TimeCode = Usd.TimeCode.Default()):
        self._warnings = warnings
        self._time = time
        self._images = ImageCache()
        self._materials: list[Material] = []
        self._ids: dict[tuple, int] = {}
        self._parsed: dict[str, _ParsedMaterial] = {}

    @property
    def materials(self) -> list[Material]:
        """Every material handed out so far; `id_for`'s return value indexes this list.

        The library's own list (it grows as `id_for` meets new materials); do not modify it.
        """
        return self._materials

    def id_for(self, material: UsdShade.Material | None, display_color: np.ndarray | None, prim_path: str) -> int:
        """The material index of a gprim.

        Args:
            material: the bound material (`ComputeBoundMaterial()[0]`), None or invalid if unbound.
            display_color: (3,) the gprim's constant displayColor, or None.
            prim_path: the gprim, named in errors.

        Returns:
            Index into `materials`. Unbound gprims share one '<displayColor>' material per distinct
            colour, or the '<fallback>' grey 0.18 material without a colour.

        Raises:
            RelightError: display_color is not 3 finite numbers, or a material input is non-finite.
        """
        color = None
        if display_color is not None:
            color = np.asarray(display_color, np.float32).reshape(-1)
            if color.shape != (3,) or not np.all(np.isfinite(color)):
                raise RelightError(f"{prim_path}: displayColor must be 3 finite numbers, got {display_color}")
        if material is None or not material.GetPrim().IsValid():
            if color is None:
                return self._intern((FALLBACK_PATH,), lambda: Material(FALLBACK_PATH))
            return self._intern(
                (DISPLAY_COLOR_PATH, tuple(color.tolist())),
                lambda: Material(DISPLAY_COLOR_PATH, diffuse_color=MaterialInput(color)),
            )
        path = str(material.GetPath())
        if path not in self._parsed:
            self._parsed[path] = self._parse(material)
        parsed = self._parsed[path]
        if not parsed.display_color_fields or color is None:
            return self._intern((path,), lambda: parsed.material)
        return self._intern(
            (path, tuple(color.tolist())),
            lambda: parsed.material.replace(
                **{
                    name: MaterialInput(fit_channels(color, getattr(parsed.material, name).value.size))
                    for name in parsed.display_color_fields
                }
            ),
        )

    def _intern(self, key: tuple, build) -> int:
        if key not in self._ids:
            self._ids[key] = len(self._materials)
            self._materials.append(build())
        return self._ids[key]

    # Reading a material network -------------------------------------------------------------

    def _warn(self, message: str) -> None:
        warn(message, self._warnings)

    def _surface_shader(self, material: UsdShade.Material) -> UsdShade.Shader | None:
        """The universal surface shader if it is one we read, else the MaterialX ('mtlx') one."""
        universal = material.ComputeSurfaceSource()[0]
        if universal and (
            universal.GetShaderId() == "UsdPreviewSurface" or universal.GetShaderId() in materialx.SURFACE_IDS
        ):
            return universal
        mtlx = material.ComputeSurfaceSource("mtlx")[0]
        return mtlx if mtlx else (universal or None)

    def _parse(self, material: UsdShade.Material) -> _ParsedMaterial:
        path = str(material.GetPath())
        shader = self._surface_shader(material)
        if not shader:
            documents = materialx.mtlx_references(material.GetPrim())
            if documents:
                return _ParsedMaterial(self._document_material(material, *documents[0]), ())
            self._warn(f"material {path} has no universal surface shader; using grey 0.18 diffuse")
            return _ParsedMaterial(Material(path), ())
        shader_id = shader.GetShaderId()
        if shader_id in materialx.SURFACE_IDS:
            return _ParsedMaterial(
                materialx.usd_surface_material(path, shader, self._time, self._images, self._warn), ()
            )
        if shader_id != "UsdPreviewSurface":
            self._warn(
                f"material {path}: surface shader '{shader_id}' is not UsdPreviewSurface; using grey 0.18 diffuse"
            )
            return _ParsedMaterial(Material(path), ())
        defaults = Material(path)
        fields = {}
        display_color_fields = []
        for input_name, field_name in _TEXTURABLE_INPUTS.items():
            default = getattr(defaults, field_name).value
            fields[field_name], reads_display_color = self._texturable_input(path, shader, input_name, default)
            if reads_display_color:
                display_color_fields.append(field_name)
        use_specular_workflow = self._parameter(path, shader, "useSpecularWorkflow")
        opacity_threshold = self._parameter(path, shader, "opacityThreshold")
        opacity_mode = self._parameter(path, shader, "opacityMode")
        if opacity_mode is not None and opacity_mode not in _OPACITY_MODES:
            self._warn(f"material {path}: unknown opacityMode '{opacity_mode}'; using 'transparent'")
            opacity_mode = None
        material_record = defaults.replace(
            use_specular_workflow=defaults.use_specular_workflow
            if use_specular_workflow is None
            else bool(use_specular_workflow),
            opacity_threshold=defaults.opacity_threshold if opacity_threshold is None else float(opacity_threshold),
            opacity_mode=defaults.opacity_mode if opacity_mode is None else str(opacity_mode),
            **fields,
        )
        return _ParsedMaterial(material_record, tuple(display_color_fields))

    def _document_material(self, material: UsdShade.Material, file: str, target: str) -> Material:
        """The material a `.mtlx` reference brings in; grey 0.18 diffuse (warned) if it cannot be read."""
        path = str(material.GetPath())
        try:
            return materialx.document_material(
                path, material.GetPrim().GetName(), file, target, self._images, self._warn
            )
        except RelightError as error:
            self._warn(f"material {path}: {error}; using grey 0.18 diffuse")
            return Material(path, documents=(file,))

    def _parameter(self, material_path: str, shader: UsdShade.Shader, name: str):
        """A node input that must be a constant (authored, or from an interface input); None if
        unauthored or (with a warning) connected to another node's output."""
        shader_input = shader.GetInput(name)
        if not shader_input:
            return None
        sources = shader_input.GetValueProducingAttributes()
        if not sources:
            return shader_input.GetAttr().Get(self._time)
        if _is_output(sources[0]):
            self._warn(
                f"material {material_path}: {shader_input.GetAttr().GetPath()} is connected to "
                f"{sources[0].GetPath()}; only a constant is supported here, using the fallback"
            )
            return None
        return sources[0].Get(self._time)

    def _constant(self, material_path: str, shader: UsdShade.Shader, name: str, default: np.ndarray) -> np.ndarray:
        """A constant node input as a float32 array, `default` where unauthored."""
        value = self._parameter(material_path, shader, name)
        if value is None:
            return default
        return _as_array(value, shader.GetInput(name).GetAttr())

    def _texturable_input(
        self, material_path: str, shader: UsdShade.Shader, name: str, default: np.ndarray
    ) -> tuple[MaterialInput, bool]:
        """A UsdPreviewSurface input: (record, whether it reads the gprim's displayColor)."""
        shader_input = shader.GetInput(name)
        if not shader_input:
            return MaterialInput(default), False
        own_value = shader_input.GetAttr().Get(self._time)
        constant = default
        if own_value is not None:
            constant = fit_channels(_as_array(own_value, shader_input.GetAttr()), default.size)
        sources = shader_input.GetValueProducingAttributes()
        if not sources:
            return MaterialInput(constant), False
        source = sources[0]
        if not _is_output(source):
            value = source.Get(self._time)
            if value is None:
                return MaterialInput(constant), False
            return MaterialInput(fit_channels(_as_array(value, source), default.size)), False
        node = UsdShade.Shader(source.GetPrim())
        node_id = node.GetShaderId() or ""
        output = UsdShade.Output(source).GetBaseName()
        if node_id == "UsdUVTexture":
            return self._texture_input(material_path, node, output, constant), False
        if node_id.startswith("UsdPrimvarReader_"):
            varname = self._parameter(material_path, node, "varname")
            fallback = self._parameter(material_path, node, "fallback")
            if fallback is not None:
                constant = fit_channels(_as_array(fallback, node.GetInput("fallback").GetAttr()), default.size)
            if varname != _DISPLAY_COLOR:
                self._warn(
                    f"material {material_path}: {node.GetPath()} reads primvar '{varname}'; only displayColor "
                    f"and st are supported, using {constant.tolist()} for {name}"
                )
            return MaterialInput(constant), varname == _DISPLAY_COLOR
        self._warn(
            f"material {material_path}: {name} is driven by unsupported node {node.GetPath()} "
            f"('{node_id}'); using {constant.tolist()}"
        )
        return MaterialInput(constant), False

    def _texture_input(
        self, material_path: str, node: UsdShade.Shader, output: str, constant: np.ndarray
    ) -> MaterialInput:
        """An input fed by a UsdUVTexture output; the constant fallback if the file is unusable.

        The fallback is the node's authored `fallback` (channels of `output`), else `constant`
        (the shader input's own value or its registered default).
        """
        fallback = None
        authored_fallback = self._parameter(material_path, node, "fallback")
        if authored_fallback is not None:
            values = _as_array(authored_fallback, node.GetInput("fallback").GetAttr())
            fallback = np.concatenate([values[:4], np.array([0, 0, 0, 1], np.float32)[values.size :]])
            constant = fit_channels(select_output(fallback, output), constant.size)
        file_path = self._texture_path(material_path, node)
        if file_path is None:
            return MaterialInput(constant)
        st_primvar, st_from_uv = self._st_mapping(material_path, node.GetInput("st"), depth=0)
        try:
            texture = load_texture(
                file_path,
                self._images,
                source_color_space=str(self._parameter(material_path, node, "sourceColorSpace") or "auto"),
                wrap_s=str(self._parameter(material_path, node, "wrapS") or "useMetadata"),
                wrap_t=str(self._parameter(material_path, node, "wrapT") or "useMetadata"),
                scale=self._constant(material_path, node, "scale", np.ones(4, np.float32)),
                bias=self._constant(material_path, node, "bias", np.zeros(4, np.float32)),
                fallback=fallback,
                output=output,
                st_primvar=st_primvar,
                st_from_uv=st_from_uv,
            )
        except RelightError as error:
            self._warn(f"material {material_path}: {error}; using the constant {constant.tolist()}")
            return MaterialInput(constant)
        return MaterialInput(constant, texture)

    def _texture_path(self, material_path: str, node: UsdShade.Shader) -> str | None:
        """The resolved image path of a UsdUVTexture, or None (with a warning) if missing."""
        file_input = node.GetInput("file")
        sources = file_input.GetValueProducingAttributes() if file_input else []
        asset = sources[0].Get(self._time) if sources and not _is_output(sources[0]) else None
        if not isinstance(asset, Sdf.AssetPath) or not asset.path:
            self._warn(f"material {material_path}: texture {node.GetPath()} has no file; using the fallback")
            return None
        if asset.resolvedPath:
            return asset.resolvedPath
        layer = sources[0].GetPropertyStack(self._time)[0].layer
        anchored = asset.path
        if layer.realPath and not os.path.isabs(asset.path):
            anchored = os.path.normpath(os.path.join(os.path.dirname(layer.realPath), asset.path))
        self._warn(f"material {material_path}: missing texture file {anchored}; using the fallback")
        return None

    def _st_mapping(self, material_path: str, st_input: UsdShade.Input, depth: int) -> tuple[str, np.ndarray]:
        """Where a float2 coordinate input comes from: (primvar name, (3, 3) st_from_uv).

        A primvar reader gives the identity; each UsdTransform2d composes
        st = R(rotation) (scale * in) + translation (Storm's order); an unconnected input is the
        constant coordinate (a zero linear part plus its value as translation).
        """
        if depth > _MAX_NODE_DEPTH:
            raise RelightError(f"material {material_path}: texture coordinate network too deep or cyclic")
        sources = st_input.GetValueProducingAttributes() if st_input else []
        if not sources or not _is_output(sources[0]):
            value = sources[0].Get(self._time) if sources else None
            st_from_uv = np.zeros((3, 3))
            st_from_uv[2, 2] = 1.0
            if value is not None:
                st_from_uv[:2, 2] = _as_array(value, sources[0])[:2]
            return "st", st_from_uv
        node = UsdShade.Shader(sources[0].GetPrim())
        node_id = node.GetShaderId()
        if node_id == "UsdPrimvarReader_float2":
            varname = str(self._parameter(material_path, node, "varname") or "")
            if varname != "st":
                self._warn(
                    f"material {material_path}: {node.GetPath()} reads texture coordinates from primvar "
                    f"'{varname}'; the walker bakes 'st'"
                )
            return varname, np.eye(3)
        if node_id == "UsdTransform2d":
            primvar, inner = self._st_mapping(material_path, node.GetInput("in"), depth + 1)
            rotation = np.radians(float(self._constant(material_path, node, "rotation", np.zeros(1, np.float32))[0]))
            scale = self._constant(material_path, node, "scale", np.ones(2, np.float32)).astype(np.float64)
            translation = self._constant(material_path, node, "translation", np.zeros(2, np.float32))
            transform = np.eye(3)
            cos, sin = np.cos(rotation), np.sin(rotation)
            transform[:2, :2] = np.array([[cos, -sin], [sin, cos]]) @ np.diag(scale[:2])
            transform[:2, 2] = translation[:2]
            return primvar, transform @ inner
        self._warn(
            f"material {material_path}: texture coordinates come from unsupported node {node.GetPath()} "
            f"('{node_id}'); using primvar 'st'"
        )
        return "st", np.eye(3)
