"""The files a session's clients may name: everything inside the session's output directory, and
for images (textures, cookies) also the shot's own folder. Paths are resolved (`..`, symbolic
links) before they are checked, and a client's lights layer may not make USD open anything else.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from pxr import Sdf, Tf

from pipeline.errors import RelightError
from relight_torch.stage import usd_error_line

LAYER_SUFFIXES = (".usda", ".usdc", ".usd")
MAX_PATH = 4096


class SessionFiles:
    """Client paths of one session.

    Args:
        out_dir: the output directory (saved and loaded layers).
        shot_dir: the shot's folder (its images may be named by texture and cookie attributes).
    """

    def __init__(self, out_dir: Path, shot_dir: Path):
        self.out_dir = out_dir.resolve()
        self.image_roots = (self.out_dir, shot_dir.resolve())
        self._scratch = tempfile.TemporaryDirectory(prefix="relight-serve-")

    def close(self) -> None:
        self._scratch.cleanup()

    def layer_path(self, path: object, must_exist: bool = True) -> Path:
        """A client's layer path as a file inside the output directory (relative paths start there).

        Raises:
            RelightError: not a file name, outside the output directory, not .usda/.usdc/.usd,
                missing when `must_exist`, or in a missing folder.
        """
        resolved = self._resolved(path, "path")
        if not resolved.is_relative_to(self.out_dir):
            raise RelightError(f"path {path!r:.120} is outside the session's output directory {self.out_dir}")
        if resolved.suffix not in LAYER_SUFFIXES:
            raise RelightError(f"path {path!r:.120} must end in {', '.join(LAYER_SUFFIXES)}")
        if must_exist and not resolved.is_file():
            raise RelightError(f"path {path!r:.120}: no such file in the session's output directory")
        if not must_exist and not resolved.parent.is_dir():
            raise RelightError(f"path {path!r:.120}: its folder does not exist in the output directory")
        return resolved

    def image_path(self, path: object) -> Path:
        """A client's image path (texture, cookie): an existing file in one of `image_roots`.

        Raises:
            RelightError: any other path.
        """
        resolved = self._resolved(path, "image")
        if not any(resolved.is_relative_to(root) for root in self.image_roots) or not resolved.is_file():
            raise RelightError(f"image {path!r:.120}: no such file in the output directory or the shot's folder")
        return resolved

    def layer_from_text(self, text: object) -> Path:
        """A client's .usda text written to a private scratch file; its path.

        Raises:
            RelightError: the text is not a .usda layer.
        """
        if not isinstance(text, str) or not _parses(text):
            raise RelightError("load: the text is not a USD layer (.usda)")
        with tempfile.NamedTemporaryFile("w", suffix=".usda", dir=self._scratch.name, delete=False) as file:
            file.write(text)
        return Path(file.name)

    def check_layer(self, layer_path: Path) -> None:
        """Refuse a client's lights layer that would make USD open files elsewhere: sublayers,
        references, payloads, or asset values outside `image_roots`.

        Raises:
            RelightError: naming the first such file.
        """
        try:
            layer = Sdf.Layer.OpenAsAnonymous(str(layer_path))
        except Tf.ErrorException as error:
            raise RelightError(f"load: {layer_path.name}: not a USD layer ({usd_error_line(error)})") from None
        if layer is None:
            raise RelightError(f"load: {layer_path.name}: not a USD layer")
        if layer.GetCompositionAssetDependencies():
            raise RelightError("load: a lights layer may not name sublayers, references or payloads")
        outside: list[str] = []

        def visit(spec_path: Sdf.Path) -> None:
            spec = layer.GetObjectAtPath(spec_path)
            value = getattr(spec, "default", None) if isinstance(spec, Sdf.AttributeSpec) else None
            if isinstance(value, Sdf.AssetPath) and value.path:
                resolved = Path(Sdf.ComputeAssetPathRelativeToLayer(layer, value.path)).resolve()
                if not any(resolved.is_relative_to(root) for root in self.image_roots):
                    outside.append(f"{spec_path} = @{value.path}@")

        layer.Traverse(Sdf.Path.absoluteRootPath, visit)
        if outside:
            raise RelightError(f"load: {outside[0]} names a file outside the output directory and the shot's folder")
        existing = Sdf.Layer.Find(str(layer_path))
        if existing is not None:  # USD keeps opened layers: compose the file as it is now
            existing.Reload(force=True)

    def _resolved(self, path: object, what: str) -> Path:
        if not isinstance(path, str) or not path or "\0" in path or len(path) > MAX_PATH:
            raise RelightError(f"{what} {path!r:.120} is not a file name")
        return (self.out_dir / path).resolve()


def _parses(text: str) -> bool:
    """Whether `text` is a .usda layer."""
    try:
        return bool(Sdf.Layer.CreateAnonymous(".usda").ImportFromString(text))
    except Tf.ErrorException:
        return False
