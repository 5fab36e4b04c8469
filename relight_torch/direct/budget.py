"""The memory budget of a relighter's per-light caches (`RelightSettings.memory_budget`): what they
hold, whether a light's transport fits, and what goes when they are over it: the transports of the
lights edited longest ago, then their unit images folded into one sum, then half precision."""

from __future__ import annotations

from collections.abc import Callable, Collection

import torch

from relight_torch.direct.rig import LightState

# total (N, 3) plus a light's image (colour, lobe multipliers and light link applied): `Relighter._add_light`.
AddLight = Callable[[torch.Tensor, LightState], torch.Tensor]


class MemoryBudget:
    """The budget of the caches of a relighter's lights, and the summed light of the lights folded to keep it.

    Args:
        limit: bytes the per-light caches (transports, unit images, progress, the folded sum) may hold.

    Attributes:
        folded: (N, 3) the summed light of the folded lights (`LightState.folded`), or None while none is.
        half_images: set once the budget asks for half-precision unit images.
    """

    def __init__(self, limit: int):
        if limit < 0:
            raise ValueError(f"memory_budget must be >= 0 bytes, got {limit}")
        self.limit = limit
        self.folded: torch.Tensor | None = None
        self.half_images = False

    def held_bytes(self, states: Collection[LightState]) -> int:
        """Bytes held by the lights' caches (transport, images, progress) and the folded lights' sum."""
        total = self.folded.numel() * self.folded.element_size() if self.folded is not None else 0
        for state in states:
            total += sum(transport.num_bytes for transport in state.transports or ())
            total += state.images.numel() * state.images.element_size() if state.images is not None else 0
            total += state.progress.num_bytes if state.progress is not None else 0
        return total

    def transport_fits(self, states: Collection[LightState], needed: int) -> bool:
        """Whether a transport of `needed` bytes, kept, would leave the caches within the budget
        (beside the lights' unit images)."""
        kept = sum(other.images.numel() * other.images.element_size() for other in states if other.images is not None)
        return kept + needed <= self.limit

    def kept(self, images: torch.Tensor) -> torch.Tensor:
        """Unit images as they are kept: in half precision once the budget asked for it."""
        return images.half() if self.half_images else images

    def drop_transports(self, states: Collection[LightState], current: LightState) -> None:
        """Bring `held_bytes` towards the budget after `current`'s images were made: drop the
        transports of the lights edited longest ago, then `current`'s own (`fold_oldest` does
        the rest once the frame is made)."""
        # The lights edited longest ago first, the one just shaded last.
        others = sorted((state for state in states if state is not current), key=lambda s: s.edited)
        for state in others + [current]:
            if self.held_bytes(states) <= self.limit:
                return
            state.transports = None

    def fold_oldest(
        self, states: Collection[LightState], active: str | None, like: torch.Tensor, add_light: AddLight
    ) -> None:
        """After a frame, bring `held_bytes` within the budget if dropping transports did not:
        fold the images of the lights edited longest ago into one sum `folded` (like `like`,
        (N, 3); the frame stays the same; an edit of a folded light makes its images again,
        `unfold`), never the `active` light's (its colour edits stay a rescale) nor images made
        elsewhere (`LightState.external`); then keep every unit image in half precision."""
        if self.held_bytes(states) <= self.limit:
            return
        for state in sorted(states, key=lambda s: s.edited):
            if self.held_bytes(states) <= self.limit:
                return
            if state.images is not None and not state.external and state.light.path != active:
                self._fold(state, like, add_light)
        if self.held_bytes(states) > self.limit and not self.half_images:
            self.half_images = True
            for state in states:
                if state.images is not None:
                    state.images = state.images.half()

    def _fold(self, state: LightState, like: torch.Tensor, add_light: AddLight) -> None:
        """Add the light's image to `folded` and drop its images and transport."""
        if self.folded is None:
            self.folded = torch.zeros_like(like)
        add_light(self.folded, state)
        state.images, state.transports, state.progress, state.folded = None, None, None, True

    def unfold(self, state: LightState, images: torch.Tensor, add_light: AddLight) -> None:
        """Before a folded light changes: give it its unit `images` again (made as before: the same
        numbers, fixed samples) and take its image out of `folded`."""
        assert self.folded is not None, "a folded light's image is in the folded sum"
        state.folded = False
        state.images = images
        image = add_light(torch.zeros_like(self.folded), state)
        self.folded.sub_(image)
