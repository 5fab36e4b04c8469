"""MaterialX pattern networks evaluated into `MaterialInput`s (a constant or one affine texture).

One evaluator serves both places a MaterialX network can live: a UsdShade network whose shaders
carry MaterialX node ids (`info:id = "ND_image_color3"`), and a `.mtlx` document read with the
`materialx` package. Each is wrapped as a `Node` (category, type, ports); a port is a constant or
a connection to another node's output, and unauthored inputs take their nodedef's default from
MaterialX's standard libraries.

A material input here is what the baker can sample: a constant, or one texture lookup through an
affine map (`Texture.scale` / `bias`). So the evaluator supports the nodes that keep that form:

* `image`, `tiledimage` (file, default, texcoord, u/vaddressmode, uvtiling, uvoffset, real-world
  sizes) and `UsdUVTexture` become textures; `texcoord`, `geompropvalue` and
  `UsdPrimvarReader` give the primvar, `multiply` / `add` / `subtract` of it by constants its
  transform;
* `constant`, `dot`, `convert` pass values through; `normalmap` turns a tangent-space image into
  the preview surface's tangent-space normal (2 v - 1, xy times its `scale`);
* `multiply`, `add`, `subtract` and `mix` where at most one operand is a texture, exactly. Where
  two are, the second is replaced by its image average, with a warning.

Any other node is replaced by the surface input's default, with a warning naming it.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Protocol

import MaterialX as mx
import numpy as np
from pxr import Sdf, Usd, UsdShade

from pipeline.errors import RelightError
from pipeline.scene.textures import (
    ImageCache,
    expand_to_rgba,
    fit_channels,
    load_texture,
    select_output,
)
from pipeline.scene.types import MaterialInput, Texture

_MAX_DEPTH = 64
# MaterialX address modes -> UsdUVTexture wrap modes ('constant' returns the image node's
# `default` outside [0, 1]: exact as 'black' when that default is 0).
_ADDRESS_MODES = {"periodic": "repeat", "clamp": "clamp", "mirror": "mirror", "constant": "black"}
_WRAP_MODES = {
    "repeat": "repeat",
    "periodic": "repeat",
    "clamp": "clamp",
    "mirror": "mirror",
    "black": "black",
    "useMetadata": "useMetadata",
}
# Colour spaces of MaterialX filename inputs -> UsdUVTexture sourceColorSpace.
_COLOR_SPACES = {
    "srgb_texture": "sRGB",
    "srgb": "sRGB",
    "g22_rec709": "sRGB",
    "lin_rec709": "raw",
    "raw": "raw",
    "": "raw",
}
_OUTPUT_INDICES = {"rgb": [0, 1, 2], "r": [0], "g": [1], "b": [2], "a": [3]}


@functools.cache
def standard_library() -> mx.Document:
    """MaterialX's standard data libraries (nodedefs and their defaults), loaded once."""
    library = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), library)
    return library


@dataclass(frozen=True)
class Port:
    """One node input: a constant `value`, or the `output` of an upstream `node`.

    Attributes:
        value: float, (C,) float32 array, string or file path (resolved, absolute) when
            unconnected; None when nothing is authored and there is no default.
        node: the upstream node, or None.
        output: the upstream output's name ('out' for single-output nodes).
        color_space: the MaterialX colour space of a filename value ('' unknown).
    """

    value: object = None
    node: Node | None = None
    output: str = "out"
    color_space: str = ""


class Node(Protocol):
    """A MaterialX node as the evaluator sees it, wherever it is authored."""

    category: str
    type: str
    name: str
    unspecified_color_space: str

    def port(self, name: str) -> Port | None:
        """The input `name` (authored, else its nodedef default), None if the node has no such input."""


def _python_value(value):
    """A MaterialX or Gf value as a float, bool, int, str or (C,) float32 array."""
    if isinstance(value, (bool, int, float, str)):
        return value
    if hasattr(value, "asTuple"):
        return np.asarray(value.asTuple(), np.float32)
    return np.atleast_1d(np.asarray(value, np.float32)).reshape(-1)


def _default_port(nodedef: mx.NodeDef | None, name: str) -> Port | None:
    if nodedef is None:
        return None
    nodedef_input = nodedef.getActiveInput(name)
    if nodedef_input is None:
        return None
    value = nodedef_input.getValue() if nodedef_input.hasValueString() and nodedef_input.getValueString() else None
    return Port(value=None if value is None else _python_value(value))


def _usd_nodedef(shader_id: str) -> mx.NodeDef | None:
    library = standard_library()
    return library.getNodeDef(shader_id) or library.getNodeDef(f"ND_{shader_id}")


class UsdNode:
    """A UsdShade shader with a MaterialX id (or UsdUVTexture / UsdPrimvarReader_float2)."""

    # MaterialX's default working space (USD stages carry none for MaterialX nodes).
    unspecified_color_space = "lin_rec709"

    def __init__(self, shader: UsdShade.Shader, time: Usd.TimeCode):
        self._shader = shader
        self._time = time
        shader_id = shader.GetShaderId() or ""
        nodedef = _usd_nodedef(shader_id)
        # USD's own nodes (UsdUVTexture, UsdPrimvarReader_float2) keep USD's defaults (wrapS
        # 'useMetadata', not MaterialX's 'periodic'): the evaluator supplies those.
        self._nodedef = nodedef if shader_id.startswith("ND_") else None
        if shader_id.startswith("UsdPrimvarReader"):
            self.category = "UsdPrimvarReader"
        else:
            self.category = nodedef.getNodeString() if nodedef else shader_id
        self.type = nodedef.getType() if nodedef else ""
        self.name = str(shader.GetPath())

    def port(self, name: str) -> Port | None:
        shader_input = self._shader.GetInput(name)
        sources = shader_input.GetValueProducingAttributes() if shader_input else []
        if sources:
            source = sources[0]
            if UsdShade.Utils.GetType(source.GetName()) == UsdShade.AttributeType.Output:
                upstream = UsdNode(UsdShade.Shader(source.GetPrim()), self._time)
                return Port(node=upstream, output=UsdShade.Output(source).GetBaseName())
            value = source.Get(self._time)
            if value is not None:
                if isinstance(value, Sdf.AssetPath):
                    value = value.resolvedPath or _anchored(value.path, source, self._time)
                return Port(value=_python_value(value), color_space=source.GetColorSpace())
        return _default_port(self._nodedef, name)


def _anchored(path: str, attribute: Usd.Attribute, time: Usd.TimeCode) -> str:
    """An unresolved asset path anchored to the layer that authors it (for the missing-file message)."""
    layer = attribute.GetPropertyStack(time)[0].layer
    if path and layer.realPath and not os.path.isabs(path):
        return os.path.normpath(os.path.join(os.path.dirname(layer.realPath), path))
    return path


class MtlxNode:
    """A node of a `.mtlx` document (its document must carry the standard library)."""

    def __init__(self, node: mx.Node, document_dir: str):
        self._node = node
        self._dir = document_dir
        self.category = node.getCategory()
        self.type = node.getType()
        self.name = node.getNamePath()
        document = node.getDocument()
        self.unspecified_color_space = document.getColorSpace() if document else ""

    def port(self, name: str) -> Port | None:
        node_input = self._node.getInput(name)
        if node_input is None:
            return _default_port(self._node.getNodeDef(), name)
        if node_input.hasInterfaceName():
            interface = node_input.getInterfaceInput()
            if interface is None:
                return _default_port(self._node.getNodeDef(), name)
            node_input = interface
        upstream = node_input.getConnectedNode()
        if upstream is not None:
            connected = node_input.getConnectedOutput()
            output = node_input.getOutputString() or (connected.getOutputString() if connected else "") or "out"
            return Port(node=MtlxNode(upstream, self._dir), output=output)
        if not node_input.getValueString():
            return _default_port(self._node.getNodeDef(), name)
        if node_input.getType() == "filename":
            path = node_input.getResolvedValueString()
            return Port(
                value=os.path.normpath(os.path.join(self._dir, path)), color_space=node_input.getActiveColorSpace()
            )
        return Port(value=_python_value(node_input.getValue()))


def as_floats(value, num_channels: int) -> np.ndarray:
    """A port value as a (num_channels,) float32 array (USD's connection conversions)."""
    try:
        array = np.atleast_1d(np.asarray(value, np.float32)).reshape(-1)
    except (TypeError, ValueError):
        raise RelightError(f"{value!r} is not a number or a vector") from None
    if not np.all(np.isfinite(array)):
        raise RelightError(f"non-finite value {value}")
    return fit_channels(array, num_channels)


# Affine arithmetic on a constant-or-texture value ------------------------------------------


def _texture_rgb(texture: Texture) -> Texture:
    """An equivalent texture whose output is 'rgb' with identity scale and bias (pixels mapped)."""
    rgba = expand_to_rgba(texture.pixels) * texture.scale + texture.bias
    pixels = fit_channels(select_output(rgba, texture.output), 3).astype(np.float32)
    return replace(
        texture,
        pixels=np.ascontiguousarray(pixels),
        scale=np.ones(4, np.float32),
        bias=np.zeros(4, np.float32),
        output="rgb",
    )


def scaled(value: MaterialInput, multiplier, offset=0.0) -> MaterialInput:
    """value * multiplier + offset, per channel; exact for a texture (folded into scale and bias).

    Args:
        value: (C,) constant, optionally textured.
        multiplier, offset: scalars or (C,) arrays.
    """
    multiplier = np.broadcast_to(np.asarray(multiplier, np.float32), value.value.shape)
    offset = np.broadcast_to(np.asarray(offset, np.float32), value.value.shape)
    constant = (value.value * multiplier + offset).astype(np.float32)
    texture = value.texture
    if texture is None or not np.any(multiplier):
        return MaterialInput(constant)
    indices = _OUTPUT_INDICES[texture.output]
    if len(indices) != multiplier.size and not (np.all(multiplier == multiplier[0]) and np.all(offset == offset[0])):
        texture = _texture_rgb(texture)
        indices = _OUTPUT_INDICES["rgb"]
    channel_multiplier = fit_channels(multiplier, len(indices))
    channel_offset = fit_channels(offset, len(indices))
    scale, bias = texture.scale.copy(), texture.bias.copy()
    scale[indices] *= channel_multiplier
    bias[indices] = bias[indices] * channel_multiplier + channel_offset
    return MaterialInput(constant, replace(texture, scale=scale, bias=bias))


def average(value: MaterialInput) -> np.ndarray:
    """(C,) the constant, or the texture's mean over its image (what a textured operand becomes
    where the form allows only one texture)."""
    if value.texture is None:
        return value.value
    texture = value.texture
    rgba = expand_to_rgba(texture.pixels) * texture.scale + texture.bias
    mean = select_output(rgba, texture.output).reshape(-1, len(_OUTPUT_INDICES[texture.output])).mean(axis=0)
    return fit_channels(mean.astype(np.float32), value.value.size)


def channel_mean(value: MaterialInput) -> MaterialInput:
    """A colour's mean over R, G, B as a (1,) value, exact for a texture (the mean is taken per texel,
    and bilinear filtering commutes with it)."""
    if value.texture is None:
        return MaterialInput(np.array([value.value.mean()], np.float32))
    rgb = _texture_rgb(value.texture)
    grey = rgb.pixels.mean(axis=-1, keepdims=True).astype(np.float32)
    return MaterialInput(np.array([value.value.mean()], np.float32), replace(rgb, pixels=grey, output="r"))


class GraphEvaluator:
    """Evaluates ports into `MaterialInput`s for one material; problems go to `warn`.

    Args:
        material_path: the material, named in warnings.
        images: the library's image cache.
        warn: one-line warning sink.
    """

    def __init__(self, material_path: str, images: ImageCache, warn: Callable[[str], None]):
        self._path = material_path
        self._images = images
        self._warn = warn

    def warn(self, message: str) -> None:
        self._warn(f"material {self._path}: {message}")

    def evaluate(self, port: Port | None, default: np.ndarray, label: str, depth: int = 0) -> MaterialInput:
        """The value of `port` as a (C,) input, C = default.size; `default` where unusable.

        Args:
            port: the port (None: the default).
            default: (C,) float32 value used for unsupported nodes and missing files.
            label: the surface input being evaluated, named in warnings.
        """
        num_channels = default.size
        if port is None or (port.node is None and port.value is None):
            return MaterialInput(default)
        if port.node is None:
            return MaterialInput(as_floats(port.value, num_channels))
        if depth > _MAX_DEPTH:
            raise RelightError(f"material {self._path}: node network too deep or cyclic at {label}")
        node = port.node
        category = node.category

        def operand(name: str, fallback: float = 0.0) -> MaterialInput:
            return self.evaluate(node.port(name), np.full(num_channels, fallback, np.float32), label, depth + 1)

        if category == "constant":
            return operand("value")
        if category in ("dot", "convert"):
            return operand("in")
        if category == "multiply":
            return self.product(operand("in1"), operand("in2", 1.0), label)
        if category in ("add", "subtract"):
            sign = 1.0 if category == "add" else -1.0
            return self._sum(operand("in1"), operand("in2"), sign, label)
        if category == "mix":
            return self.mix(
                operand("fg"),
                operand("bg"),
                self.evaluate(node.port("mix"), np.zeros(1, np.float32), label, depth + 1),
                label,
            )
        if category == "normalmap":
            strength = float(as_floats(self._constant(node, "scale", 1.0), 1)[0])
            encoded = self.evaluate(node.port("in"), np.array([0.5, 0.5, 1.0], np.float32), label, depth + 1)
            return scaled(fit_input(encoded, 3), [2 * strength, 2 * strength, 2], [-strength, -strength, -1])
        if category in ("image", "tiledimage", "UsdUVTexture"):
            return self._image(node, port.output, default, label, depth)
        self.warn(
            f"{label} is driven by unsupported MaterialX node {node.name} ('{category}'); using {default.tolist()}"
        )
        return MaterialInput(default)

    def _constant(self, node: Node, name: str, default):
        """A node input that must be constant; `default` (with a warning if connected) otherwise."""
        port = node.port(name)
        if port is None or port.value is None:
            return default
        if port.node is not None:
            self.warn(f"{node.name}.{name} is connected; only a constant is supported there, using {default}")
            return default
        return port.value

    def product(self, first: MaterialInput, second: MaterialInput, label: str) -> MaterialInput:
        if first.texture is None:
            return scaled(second, first.value)
        if second.texture is not None:
            self.warn(f"{label} multiplies two textures; the second is replaced by its image average")
        return scaled(first, average(second))

    def _sum(self, first: MaterialInput, second: MaterialInput, sign: float, label: str) -> MaterialInput:
        if first.texture is None:
            return scaled(second, sign, first.value)
        if second.texture is not None:
            self.warn(f"{label} adds two textures; the second is replaced by its image average")
        return scaled(first, 1.0, sign * average(second))

    def mix(self, fg: MaterialInput, bg: MaterialInput, weight: MaterialInput, label: str) -> MaterialInput:
        """fg * weight + bg * (1 - weight) (MaterialX `mix`); exact while one operand is textured."""
        if weight.texture is None:
            amount = float(weight.value[0])
            if amount == 0.0:
                return bg
            if amount == 1.0:
                return fg
            return self._sum(scaled(fg, amount), scaled(bg, 1.0 - amount), 1.0, label)
        if fg.texture is None and bg.texture is None:
            return scaled(fit_input(weight, fg.value.size), fg.value - bg.value, bg.value)
        self.warn(f"{label} mixes textures by a textured weight; the weight is replaced by its image average")
        return self.mix(fg, bg, MaterialInput(average(weight)), label)

    # Images ---------------------------------------------------------------------------------

    def _image(self, node: Node, output: str, default: np.ndarray, label: str, depth: int) -> MaterialInput:
        """An image node (MaterialX image / tiledimage, or UsdUVTexture) as a textured input."""
        num_channels = default.size
        usd_texture = node.category == "UsdUVTexture"
        fallback_name = "fallback" if usd_texture else "default"
        fallback_value = self._constant(node, fallback_name, None)
        constant = default
        if fallback_value is not None:
            values = np.atleast_1d(np.asarray(fallback_value, np.float32)).reshape(-1)
            if usd_texture:
                rgba = np.concatenate([values[:4], np.array([0, 0, 0, 1], np.float32)[values.size :]])
                values = select_output(rgba, output if output in _OUTPUT_INDICES else "rgb")
            constant = fit_channels(values, num_channels)
        file_port = node.port("file")
        path = file_port.value if file_port is not None and file_port.node is None else None
        if not path:
            self.warn(f"image {node.name} has no file; using {constant.tolist()} for {label}")
            return MaterialInput(constant)
        if usd_texture:
            texture_output = output if output in _OUTPUT_INDICES else "rgb"
            wrap = [_WRAP_MODES.get(str(self._constant(node, name, "useMetadata"))) for name in ("wrapS", "wrapT")]
            source_color_space = str(self._constant(node, "sourceColorSpace", "auto"))
            scale = as_floats(self._constant(node, "scale", np.ones(4)), 4)
            bias = as_floats(self._constant(node, "bias", np.zeros(4)), 4)
            primvar, st_from_uv = self._texcoord(node.port("st"), label, depth)
        else:
            texture_output = "r" if node.type in ("float", "integer") else "rgb"
            modes = (
                ("periodic", "periodic")
                if node.category == "tiledimage"
                else (
                    str(self._constant(node, "uaddressmode", "periodic")),
                    str(self._constant(node, "vaddressmode", "periodic")),
                )
            )
            wrap = [_ADDRESS_MODES.get(mode) for mode in modes]
            source_color_space = self._color_space(node, file_port, label)
            scale, bias = None, None
            primvar, st_from_uv = self._texcoord(node.port("texcoord"), label, depth)
            if node.category == "tiledimage":
                st_from_uv = self._tiling(node) @ st_from_uv
        if None in wrap:
            self.warn(f"image {node.name}: unknown address mode; using 'periodic'")
            wrap = [mode or "repeat" for mode in wrap]
        try:
            texture = load_texture(
                path,
                self._images,
                source_color_space=source_color_space,
                wrap_s=wrap[0],
                wrap_t=wrap[1],
                scale=scale,
                bias=bias,
                output=texture_output,
                st_primvar=primvar,
                st_from_uv=st_from_uv,
            )
        except RelightError as error:
            self.warn(f"{error}; using the constant {constant.tolist()} for {label}")
            return MaterialInput(constant)
        return MaterialInput(constant, texture)

    def _color_space(self, node: Node, file_port: Port, label: str) -> str:
        """sourceColorSpace of a MaterialX image: raw for data (float and vector images are never
        colour-managed), else the filename's colour space, else the working space (the
        document's for `.mtlx`, lin_rec709 in USD)."""
        if node.type not in ("color3", "color4"):
            return "raw"
        name = file_port.color_space or node.unspecified_color_space
        if name not in _COLOR_SPACES:
            self.warn(f"image {node.name}: colour space '{name}' is not supported; reading it as raw for {label}")
            return "raw"
        return _COLOR_SPACES[name]

    def _tiling(self, node: Node) -> np.ndarray:
        """(3, 3) st_from_uv of a tiledimage: st = (uv * uvtiling - uvoffset) / realworldimagesize
        * realworldtilesize (MaterialX's NG_tiledimage)."""
        tiling = as_floats(self._constant(node, "uvtiling", np.ones(2)), 2)
        offset = as_floats(self._constant(node, "uvoffset", np.zeros(2)), 2)
        image_size = as_floats(self._constant(node, "realworldimagesize", np.ones(2)), 2)
        tile_size = as_floats(self._constant(node, "realworldtilesize", np.ones(2)), 2)
        ratio = tile_size / image_size
        transform = np.eye(3)
        transform[[0, 1], [0, 1]] = tiling * ratio
        transform[:2, 2] = -offset * ratio
        return transform

    def _texcoord(self, port: Port | None, label: str, depth: int) -> tuple[str, np.ndarray]:
        """(primvar name, (3, 3) st_from_uv) of a texture-coordinate port."""
        if port is None or port.node is None:
            if port is not None and port.value is not None:
                st_from_uv = np.zeros((3, 3))
                st_from_uv[2, 2] = 1.0
                st_from_uv[:2, 2] = as_floats(port.value, 2)
                return "st", st_from_uv
            return "st", np.eye(3)
        if depth > _MAX_DEPTH:
            raise RelightError(f"material {self._path}: texture coordinate network too deep or cyclic")
        node = port.node
        if node.category == "texcoord":
            if int(self._constant(node, "index", 0)) != 0:
                self.warn(
                    f"{node.name} reads texture coordinate set {self._constant(node, 'index', 0)}; "
                    f"the walker bakes 'st'"
                )
            return "st", np.eye(3)
        if node.category in ("geompropvalue", "UsdPrimvarReader"):
            name = str(self._constant(node, "geomprop" if node.category == "geompropvalue" else "varname", "st"))
            if name != "st":
                self.warn(f"{node.name} reads texture coordinates from primvar '{name}'; the walker bakes 'st'")
            return name, np.eye(3)
        if node.category in ("multiply", "add", "subtract", "divide"):
            primvar, inner = self._texcoord(node.port("in1"), label, depth + 1)
            operand = as_floats(self._constant(node, "in2", 1.0 if node.category in ("multiply", "divide") else 0.0), 2)
            transform = np.eye(3)
            if node.category == "multiply":
                transform[[0, 1], [0, 1]] = operand
            elif node.category == "divide":
                transform[[0, 1], [0, 1]] = 1.0 / operand
            else:
                transform[:2, 2] = operand if node.category == "add" else -operand
            return primvar, transform @ inner
        self.warn(
            f"texture coordinates for {label} come from unsupported node {node.name} ('{node.category}'); "
            f"using primvar 'st'"
        )
        return "st", np.eye(3)


def fit_input(value: MaterialInput, num_channels: int) -> MaterialInput:
    """The same input widened or narrowed to `num_channels` (its texture's output selects the rest)."""
    return MaterialInput(fit_channels(value.value, num_channels), value.texture)
