"""What the indirect relighters share: the direct Relighter holds the lights; each method adds an
indirect image and keeps per-light work keyed by light path, dropped when a light goes away."""

from __future__ import annotations

import torch

from relight_torch.lights.light import Light
from relight_torch.relighter import Relighter


class IndirectRelighter:
    """Base of `TransferRelighter` and `GatherRelighter`.

    Subclasses set `self._per_light` (light path -> cached indirect work) and implement
    `indirect_image()`.

    Args:
        direct: the direct relighter of the same cache; it owns the light rig.
    """

    def __init__(self, direct: Relighter):
        self.direct = direct
        self._per_light: dict[str, object] = {}

    @property
    def lights(self) -> list[Light]:
        return self.direct.lights

    def set_lights(self, lights: list[Light]) -> None:
        """Replace the whole rig; unchanged lights keep their cached work."""
        self.direct.set_lights(lights)
        for path in set(self._per_light) - {light.path for light in lights}:
            del self._per_light[path]

    def set_light(self, light: Light) -> None:
        """Add or edit a light (matched by path)."""
        self.direct.set_light(light)

    def remove_light(self, path: str) -> None:
        self.direct.remove_light(path)
        self._per_light.pop(path, None)

    def render(self) -> torch.Tensor:
        """(H, W, 3) linear image: direct (supersampled) + indirect (per pixel), exposure applied."""
        return self.direct.render() + self.indirect_image()

    def indirect_image(self) -> torch.Tensor:
        """(H, W, 3) indirect light alone, camera exposure applied."""
        raise NotImplementedError
