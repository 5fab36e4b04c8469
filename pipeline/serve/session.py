"""One light-editing session over a baked cache: the rig, its undo history, and its frames.

Edits (HTTP requests from any number of clients) change the session's `Rig` under a lock and bump
its `version`; they never touch the relighter. Frames come from one function, `Session.frames()`,
which brings the relighter up to the current rig (only the lights that changed) and yields the
frames of that version: coarse progressive frames first where the method refines progressively
(direct, transfer and the shot cache), the converged render last. A renderer calling it (`pipeline.serve.stream`)
stops consuming as soon as a newer version exists, so edits that arrive while a frame renders are
coalesced (the latest wins) and no stale frame is queued.

A saved layer holds only what changed against the shot's own lights
(`relight_torch.lights.overrides`), so `relight render CACHE --lights SAVED` renders the session's
rig. Client paths (save, load, textures) are confined to the session's output directory (images
also to the shot's folder; `pipeline.serve.files`).
"""

from __future__ import annotations

import dataclasses
import os
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pxr import Sdf

from pipeline.errors import RelightError
from pipeline.serve.attributes import edited_light, light_attributes
from pipeline.serve.files import SessionFiles
from pipeline.serve.placement import SurfaceLookup, aimed_at, along_normal, facing, new_light
from pipeline.serve.rig import SWITCHES, MaterialEdits, Rig, RigLight, silenced
from relight_torch import open_cache
from relight_torch.brdf.preview_surface import USD_INPUT_FIELDS
from relight_torch.cache.layer import CacheDescription, read_cache_layer
from relight_torch.cache.load import load_gbuffer
from relight_torch.direct.loading import shot_lights
from relight_torch.direct.rig import light_group
from relight_torch.direct.settings import RelightSettings
from relight_torch.io.exr import read_rgb_exr
from relight_torch.lights.light import Light, LightKind
from relight_torch.lights.overrides import export_layer, light_overrides_layer
from relight_torch.material_edits import (
    check_material_values,
    layer_material_edits,
    prim_material_paths,
    relighter_layer_edits,
    write_material_edits,
)
from relight_torch.methods import relight_method
from relight_torch.progressive import CostModel, progressive_frames
from relight_torch.protocol import CacheRelighter

MAX_UNDO = 1000
"""Undo steps kept (a step is a tuple of references to frozen lights)."""


@dataclass(frozen=True)
class Frame:
    """One frame of a rig version.

    Attributes:
        version: the session version it shows.
        image: (H, W, 3) float32 linear radiance, camera exposure applied (`CacheRelighter.render`).
        groups: light group -> (H, W, 3) image (`CacheRelighter.light_group_images`), or None when
            not asked for.
        final: the last frame of its version (progressive refinement yields earlier ones first).
    """

    version: int
    image: np.ndarray
    groups: dict[str, np.ndarray] | None = None
    final: bool = True


class Session:
    """A live editing session: see the module doc.

    Args:
        relighter: the cache's relighter, its lights the session's first rig.
        description: the cache layer's record.
        shot: the shot's own lights (what a saved layer is relative to).
        lookup: the deep framebuffer's pixel -> surface lookup (click placement).
        files: the paths clients may name.
        reference: (H, W, 3) float32 image to compare against, or None.
        materials: the first rig's material edits (material prim path -> {field: constant}).
    """

    def __init__(
        self,
        relighter: CacheRelighter,
        description: CacheDescription,
        shot: list[Light],
        lookup: SurfaceLookup,
        files: SessionFiles,
        reference: np.ndarray | None = None,
        materials: dict[str, dict[str, object]] | None = None,
    ):
        self.description = description
        self.files = files
        self.reference = reference
        self.width, self.height = lookup.size
        self._relighter = relighter
        self._shot = shot
        self._lookup = lookup
        self._lock = threading.RLock()
        self.changed = threading.Condition(self._lock)
        """Notified on every rig change (and by renderers poking each other)."""
        self._render_lock = threading.Lock()
        self._costs = CostModel()  # the progressive first-frame budget's cost model, kept across edits
        self._rig = Rig.of(relighter.lights, materials)
        self._sent: dict[str, tuple[Light, bool]] = {light.path: (light, True) for light in relighter.lights}
        self._sent_materials: MaterialEdits = ()  # the relighter's materials are the baked ones
        self._undo: list[Rig] = []
        self._redo: list[Rig] = []
        self._gesture: str | None = None
        self.version = 0

    @classmethod
    def open(
        cls,
        cache: str | os.PathLike[str],
        lights_layer: str | os.PathLike[str] | None = None,
        reference: str | os.PathLike[str] | None = None,
        out_dir: str | os.PathLike[str] = ".",
        device: str = "cpu",
        shadows: str = "embree",
        settings: RelightSettings = RelightSettings(),
        materials_layer: str | os.PathLike[str] | None = None,
    ) -> Session:
        """Open a cache for editing with the relighter's `settings` (its memory budget), the first
        rig holding the material edits of `materials_layer` (`material_edits.relighter_layer_edits`).

        Raises:
            RelightError: the cache cannot be opened, is of a method that needs a view (its camera
                moves), the reference's size is not the frame's, `out_dir` is no folder, or the
                materials layer cannot be applied.
        """
        description = read_cache_layer(cache)
        if relight_method(description.method).needs_view:
            raise RelightError(
                f"{cache}: a {description.method!r} cache renders views of a moving camera; serve "
                f"relights a cache baked for one camera"
            )
        if not Path(out_dir).is_dir():
            raise RelightError(f"--out {out_dir}: not a folder")
        relighter = open_cache(cache, device=device, shadows=shadows, lights_layer=lights_layer, settings=settings)
        materials = None
        if materials_layer is not None:
            try:
                materials = relighter_layer_edits(relighter, description, materials_layer)
            except RelightError as error:
                raise RelightError(f"--materials: {cache}: {error}") from None
        lookup = SurfaceLookup(load_gbuffer(Path(cache), description), description.supersampling)
        image = None
        if reference is not None:
            image = read_rgb_exr(reference)
            width, height = description.resolution
            if image.shape != (height, width, 3):
                raise RelightError(
                    f"--reference {reference}: {image.shape[1]}x{image.shape[0]}, the cache renders {width}x{height}"
                )
        files = SessionFiles(Path(out_dir), Path(description.source).parent)
        return cls(relighter, description, shot_lights(description), lookup, files, image, materials)

    def close(self) -> None:
        self.files.close()

    # --- reading -------------------------------------------------------------------------------

    def state(self) -> dict[str, Any]:
        """The rig as JSON: version, undo/redo availability, light groups and each light."""
        with self._lock:
            rig, version = self._rig, self.version
            can_undo, can_redo = bool(self._undo), bool(self._redo)
        lights = [
            {
                "path": entry.light.path,
                "type": entry.light.kind.value,
                "group": light_group(entry.light),
                "enabled": entry.enabled,
                "muted": entry.muted,
                "soloed": entry.soloed,
                "audible": rig.audible(entry),
                "lightLink": list(entry.light.light_link) if entry.light.light_link is not None else None,
                "shadowLink": list(entry.light.shadow_link) if entry.light.shadow_link is not None else None,
                "attributes": light_attributes(entry.light),
            }
            for entry in rig.lights
        ]
        groups = sorted({light["group"] for light in lights})
        names = {field: f"inputs:{name}" for name, field in USD_INPUT_FIELDS.items()}
        materials = {
            path: {names[field]: list(value) if isinstance(value, tuple) else value for field, value in edits}
            for path, edits in rig.materials
        }
        return {
            "version": version,
            "canUndo": can_undo,
            "canRedo": can_redo,
            "groups": groups,
            "lights": lights,
            "materialEdits": self._relighter.material_edits,
            "materialPaths": prim_material_paths(self._relighter.material_paths or []),
            "materials": materials,
        }

    # --- edits (each one undo step, except consecutive edits of one gesture) -------------------

    def edit(self, path: str, values: dict[str, Any], gesture: str | None = None) -> int:
        """Set attribute values and switches ('enabled', 'muted', 'soloed') of the light at `path`.

        Args:
            gesture: consecutive edits with the same non-empty gesture id (a slider drag) make one
                undo step.

        Returns:
            The new version.

        Raises:
            UnknownLight: no light at `path`.
            RelightError: a bad attribute name or value (the rig is unchanged).
        """
        if not isinstance(values, dict) or not values:
            raise RelightError(f"{path}: an edit is a non-empty JSON object of attribute values")
        with self._lock:
            entry = self._rig.find(path)
            switches = {name: values[name] for name in SWITCHES if name in values}
            for name, value in switches.items():
                if not isinstance(value, bool):
                    raise RelightError(f"{path}: {name} = {value!r:.80} is not a bool")
            attributes = {name: value for name, value in values.items() if name not in SWITCHES}
            light = edited_light(entry.light, attributes, self.files.image_path) if attributes else entry.light
            return self._commit(self._rig.replaced(dataclasses.replace(entry, light=light, **switches)), gesture)

    def edit_material(self, path: str, values: dict[str, Any], gesture: str | None = None) -> int:
        """Set UsdPreviewSurface inputs ('inputs:diffuseColor': [r, g, b], 'inputs:roughness': 0.4,
        ...) of the material at prim `path`, over its earlier edits (one undo step, as `edit`).

        Returns:
            The new version.

        Raises:
            RelightError: the cache's method has no material edits, no material at `path`, or a bad
                input name or value (the rig is unchanged).
        """
        if not self._relighter.material_edits:
            raise RelightError(f"{path}: a {self.description.method!r} cache's light transport holds its materials")
        if not isinstance(values, dict) or not values:
            raise RelightError(f"{path}: a material edit is a non-empty JSON object of input values")
        fields = {}
        for name, value in values.items():
            if name.removeprefix("inputs:") not in USD_INPUT_FIELDS:
                inputs = ", ".join(f"inputs:{input_name}" for input_name in USD_INPUT_FIELDS)
                raise RelightError(f"{path}: {name!r:.80} is not a UsdPreviewSurface input ({inputs})")
            fields[USD_INPUT_FIELDS[name.removeprefix("inputs:")]] = tuple(value) if isinstance(value, list) else value
        check_material_values(path, fields)  # before the rig takes them
        with self._lock:
            if path not in (self._relighter.material_paths or ()):
                raise RelightError(f"{path}: no material of the cache at this prim (GET /api/lights lists them)")
            return self._commit(self._rig.with_material(path, fields), gesture)

    def add(self, kind: str, path: str | None = None, values: dict[str, Any] | None = None) -> str:
        """Add a light of UsdLux type `kind`, facing the surface at the image centre.

        Args:
            path: its prim path (default: `<parent of the first light>/<kind><n>`).
            values: attribute values set on it (as `edit`).

        Returns:
            The new light's prim path.

        Raises:
            RelightError: an unknown type, a bad or taken path, or a bad value.
        """
        kinds = {k.value: k for k in LightKind}
        if kind not in kinds:
            raise RelightError(f"type {kind!r:.80} is not a UsdLux light type ({', '.join(kinds)})")
        with self._lock:
            path = self._new_path(kinds[kind]) if path is None else self._checked_new_path(path)
            light = new_light(kinds[kind], path, self._lookup, self.description.world_from_camera)
            if values:
                light = edited_light(light, values, self.files.image_path)
            self._commit(self._rig.replaced(RigLight(light)))
            return path

    def remove(self, path: str) -> int:
        """Remove the light at `path` (a saved layer deactivates a light of the shot).

        Raises:
            UnknownLight: no light at `path`.
        """
        with self._lock:
            return self._commit(self._rig.without(path))

    def place(self, path: str, x: int, y: int, mode: str = "aim", distance: float | None = None) -> int:
        """Aim the light at what pixel (x, y) sees, or put it along that surface's normal.

        Args:
            mode: 'aim' (turn in place to face the point) or 'normal' (move to `distance` along the
                normal, facing the point). A DistantLight is turned to shine along -normal either way.
            distance: world units from the surface for 'normal' (default: the light's distance now).

        Raises:
            UnknownLight: no light at `path`.
            RelightError: a bad mode, distance or pixel, a pixel that sees no surface, or a DomeLight.
        """
        if mode not in ("aim", "normal"):
            raise RelightError(f"place: mode must be 'aim' or 'normal', got {mode!r:.80}")
        for name, value in (("x", x), ("y", y)):
            if not isinstance(value, int) or isinstance(value, bool):
                raise RelightError(f"place: {name} must be an integer pixel, got {value!r:.80}")
        if distance is not None and not (
            isinstance(distance, (int, float)) and not isinstance(distance, bool) and 0 < distance < 1e15
        ):
            raise RelightError(f"place: distance must be a number > 0 and < 1e15, got {distance!r:.80}")
        try:
            point = self._lookup.at(x, y)
        except ValueError as error:
            raise RelightError(f"place: {error}") from None
        if point is None:
            raise RelightError(f"place: pixel ({x}, {y}) sees no surface")
        up = self.description.world_from_camera[:3, 1]
        with self._lock:
            entry = self._rig.find(path)
            light = entry.light
            if light.kind is LightKind.DOME:
                raise RelightError(f"{path}: a DomeLight surrounds the scene; it cannot be placed")
            if light.kind is LightKind.DISTANT:
                world_from_light = facing(light.world_from_light, -point.normal, up)
            elif mode == "aim":
                try:
                    world_from_light = aimed_at(light.world_from_light, point.position, up)
                except ValueError as error:
                    raise RelightError(f"{path}: {error}") from None
            else:
                if distance is None:
                    distance = float(np.linalg.norm(light.world_from_light[:3, 3] - point.position)) or 1.0
                world_from_light = along_normal(light.world_from_light, point, float(distance), up)
            moved = dataclasses.replace(light, world_from_light=world_from_light)
            return self._commit(self._rig.replaced(dataclasses.replace(entry, light=moved)))

    def undo(self) -> int:
        """Go back one step. Raises RelightError when there is none."""
        return self._step(self._undo, self._redo, "undo")

    def redo(self) -> int:
        """Go forward one undone step. Raises RelightError when there is none."""
        return self._step(self._redo, self._undo, "redo")

    def _step(self, source: list[Rig], target: list[Rig], name: str) -> int:
        """Make the last rig of `source` current, the current one going to `target`."""
        with self._lock:
            if not source:
                raise RelightError(f"nothing to {name}")
            target.append(self._rig)
            self._gesture = None
            return self._set(source.pop())

    # --- layers --------------------------------------------------------------------------------

    def save_text(self) -> str:
        """The layer of what changed against the shot: its lights (`light_overrides_layer`) and
        materials (`write_material_edits`), as `.usda` text."""
        with self._lock:
            rig = self._rig
        return str(self._saved_layer(rig).ExportToString())

    def _saved_layer(self, rig: Rig) -> Sdf.Layer:
        """What `save` writes: `relight render CACHE --lights L --materials L` renders the rig."""
        layer = light_overrides_layer(self._shot, rig.saved_lights())
        if rig.materials:
            write_material_edits(layer, self.description, rig.material_edits())
        return layer

    def save(self, path: str) -> Path:
        """Write the changes layer to `path` inside the output directory; returns the file.

        Raises:
            RelightError: a path outside the output directory, of another suffix than .usda,
                .usdc or .usd, or that cannot be written.
        """
        target = self.files.layer_path(path, must_exist=False)
        with self._lock:
            rig = self._rig
        try:
            export_layer(target, self._saved_layer(rig))
        except OSError as error:
            raise RelightError(f"save: {path!r:.120}: {error.strerror or error}") from None
        return target

    def load(self, path: str | None = None, text: str | None = None) -> int:
        """Make the rig the shot's lights with a layer composed over them (one undo step).

        Args:
            path: a layer inside the output directory, or
            text: a layer's .usda text.

        Raises:
            RelightError: neither or both given, a path outside the output directory, a layer that
                does not parse or names other files (`SessionFiles.check_layer`), or a bad light.
        """
        if (path is None) == (text is None):
            raise RelightError("load: give either a layer path or a layer's text")
        layer_path = self.files.layer_from_text(text) if text is not None else self.files.layer_path(path)
        self.files.check_layer(layer_path)
        lights = shot_lights(self.description, layer_path)
        materials = None
        if self._relighter.material_edits:
            materials = layer_material_edits(self.description, layer_path, self._relighter.material_paths)
        with self._lock:
            return self._commit(Rig.of(lights, materials))

    # --- frames ---------------------------------------------------------------------------------

    def frames(self, groups: bool = False) -> Iterator[Frame]:
        """The frames of the current rig, the converged one last; a progressive relighter
        (`relight_torch.progressive`) yields its coarse frames first, within the first-frame budget
        after an edit. The relighter is used by one caller at a time.

        Args:
            groups: also render each light group's image.
        """
        with self._render_lock:
            with self._lock:
                rig, version = self._rig, self.version
            self._sync(rig)
            if self._relighter.progressive:
                for step in progressive_frames(self._relighter, costs=self._costs):
                    if not step.done:
                        yield Frame(version, step.image.cpu().numpy(), None, final=False)
                exact = step.image  # the last step is the exact frame, `render()`
            else:
                exact = self._relighter.render()
            image = exact.cpu().numpy()
            group_images = None
            if groups:
                group_images = {name: im.cpu().numpy() for name, im in self._relighter.light_group_images().items()}
            yield Frame(version, image, group_images)

    # --- internals ------------------------------------------------------------------------------

    def _commit(self, rig: Rig, gesture: str | None = None) -> int:
        if not (gesture and gesture == self._gesture):
            self._undo.append(self._rig)
            del self._undo[:-MAX_UNDO]
        self._redo.clear()
        self._gesture = gesture
        return self._set(rig)

    def _set(self, rig: Rig) -> int:
        self._rig = rig
        self.version += 1
        self.changed.notify_all()
        return self.version

    def _sync(self, rig: Rig) -> None:
        """Bring the relighter to `rig`: set only the lights whose object or audibility changed, and
        the material edits when they changed."""
        if rig.materials != self._sent_materials:
            self._relighter.set_material_edits(rig.material_edits())
            self._sent_materials = rig.materials
        wanted = {light.path: (light, audible) for light, audible in rig.rendered_lights()}
        for path in [path for path in self._sent if path not in wanted]:
            self._relighter.remove_light(path)
            del self._sent[path]
        for path, (light, audible) in wanted.items():
            sent = self._sent.get(path)
            if sent is None or sent[0] is not light or sent[1] != audible:
                self._relighter.set_light(light if audible else silenced(light))
                self._sent[path] = (light, audible)

    def _new_path(self, kind: LightKind) -> str:
        paths = self._rig.paths()
        parent = Sdf.Path(paths[0]).GetParentPath() if paths else Sdf.Path("/Lights")
        if parent == Sdf.Path.absoluteRootPath:
            parent = Sdf.Path("/Lights")
        number = 1
        while str(parent.AppendChild(f"{kind.value}{number}")) in paths:
            number += 1
        return str(parent.AppendChild(f"{kind.value}{number}"))

    def _checked_new_path(self, path: Any) -> str:
        if not isinstance(path, str) or not Sdf.Path.IsValidPathString(path):
            raise RelightError(f"path {path!r:.120} is not a USD prim path")
        prim_path = Sdf.Path(path)
        if not (prim_path.IsAbsolutePath() and prim_path.IsPrimPath()):
            raise RelightError(f"path {path!r:.120} is not an absolute prim path")
        if str(prim_path) in self._rig.paths():
            raise RelightError(f"{path}: a light already exists at this prim")
        return str(prim_path)
