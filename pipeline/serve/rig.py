"""The light rig of an editing session: lights with their enable, mute and solo switches, and the
session's material edits.

A `Rig` is immutable, so undo and redo keep whole rigs (a rig shares its frozen `Light`s with the
ones before it: a step costs a tuple). Meaning of the switches:

- `enabled` is part of the shot: a disabled light is not rendered and a saved layer deactivates it;
- `muted` and `soloed` are listening aids, as on a mixing desk: they change the frame (a muted
  light, or any light but the soloed ones when one is soloed, is silent) but not the rig a saved
  layer holds.

A silent light stays in the relighter with intensity 0, so switching it back on reuses its cached
shadow rays (an intensity is a colour edit for every relighter).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from relight_torch.lights.light import Light

SWITCHES = ("enabled", "muted", "soloed")


class UnknownLight(LookupError):
    """No light at the prim path a client named."""


@dataclass(frozen=True)
class RigLight:
    """One light of the session and its switches."""

    light: Light
    enabled: bool = True
    muted: bool = False
    soloed: bool = False


MaterialEdits = tuple[tuple[str, tuple[tuple[str, object], ...]], ...]
"""Material prim path -> its edited inputs (`PreviewSurfaceParams` field, constant), as sorted pairs."""


@dataclass(frozen=True)
class Rig:
    """The session's lights, in the order they were added, and its material edits."""

    lights: tuple[RigLight, ...]
    materials: MaterialEdits = ()

    @staticmethod
    def of(lights: list[Light], materials: dict[str, dict[str, object]] | None = None) -> Rig:
        return Rig(tuple(RigLight(light) for light in lights), _frozen(materials or {}))

    def material_edits(self) -> dict[str, dict[str, object]]:
        """Material prim path -> {field: constant} of every edited material."""
        return {path: dict(values) for path, values in self.materials}

    def with_material(self, path: str, values: dict[str, object]) -> Rig:
        """This rig with `values` set on the material at `path` (over its earlier edits)."""
        edits = self.material_edits()
        edits[path] = {**edits.get(path, {}), **values}
        return dataclasses.replace(self, materials=_frozen(edits))

    def with_lights(self, lights: tuple[RigLight, ...]) -> Rig:
        return dataclasses.replace(self, lights=lights)

    def find(self, path: str) -> RigLight:
        """The light at prim `path`.

        Raises:
            UnknownLight: no light there (naming the prims there are).
        """
        for entry in self.lights:
            if entry.light.path == path:
                return entry
        raise UnknownLight(f"{path}: no light at this prim (lights: {', '.join(self.paths()) or 'none'})")

    def paths(self) -> list[str]:
        return [entry.light.path for entry in self.lights]

    def replaced(self, entry: RigLight) -> Rig:
        """This rig with `entry` in place of the light at its path, or added at the end."""
        if entry.light.path not in self.paths():
            return self.with_lights((*self.lights, entry))
        return self.with_lights(tuple(entry if e.light.path == entry.light.path else e for e in self.lights))

    def without(self, path: str) -> Rig:
        self.find(path)
        return self.with_lights(tuple(e for e in self.lights if e.light.path != path))

    def audible(self, entry: RigLight) -> bool:
        """Whether the light is heard in the frame (enabled, not muted, soloed when any is)."""
        any_solo = any(e.soloed for e in self.lights)
        return entry.enabled and not entry.muted and (entry.soloed or not any_solo)

    def saved_lights(self) -> list[Light]:
        """The rig a saved layer holds: the enabled lights."""
        return [entry.light for entry in self.lights if entry.enabled]

    def rendered_lights(self) -> list[tuple[Light, bool]]:
        """(light, audible) of every light, for the relighter (silent ones go in with intensity 0)."""
        return [(entry.light, self.audible(entry)) for entry in self.lights]


def _frozen(materials: dict[str, dict[str, object]]) -> MaterialEdits:
    """Material edits as a `Rig` keeps them (sorted pairs, comparable and hashable)."""
    return tuple(sorted((path, tuple(sorted(values.items()))) for path, values in materials.items()))


def silenced(light: Light) -> Light:
    """The light as the relighter gets it while silent."""
    return dataclasses.replace(light, intensity=0.0)
