"""What every relighter offers, whatever its method: the `CacheRelighter` protocol.

`relight_torch.open_cache` returns one; `relight render`, the bench and the quality sizing use
nothing else. Each method's relighter class satisfies it structurally (no base class):
`tests/test_methods_registry.py` checks each with `isinstance` and calls every member.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, NoReturn, Protocol, runtime_checkable

import torch

from relight_torch.errors import RelightError
from relight_torch.lights.light import Light

if TYPE_CHECKING:  # the direct package imports this module
    from relight_torch.direct.gradients import LightPose


@runtime_checkable
class CacheRelighter(Protocol):
    """A relighter of one baked cache.

    Attributes:
        material_edits: whether `edit_material` changes the image without a re-bake (a
            capability: callers test it, never the method's name).
        progressive: whether `pending` and `refine` give coarse frames (progressive refinement,
            `relight_torch.progressive`); where False they raise `RelightError`.
    """

    material_edits: bool
    progressive: bool

    @property
    def lights(self) -> list[Light]:
        """The current rig, in the order lights were added."""

    @property
    def material_paths(self) -> list[str] | None:
        """The material prim path of each material id (what `edit_material` takes by path); None
        for a cache baked before they were stored, or a relighter without material edits."""

    def set_lights(self, lights: list[Light]) -> None:
        """Replace the whole rig; unchanged lights keep their cached work."""

    def set_light(self, light: Light) -> None:
        """Add a light or edit one (matched by `light.path`); only what the edit touches is recomputed."""

    def remove_light(self, path: str) -> None:
        """Remove the light with prim path `path`."""

    def render(self) -> torch.Tensor:
        """(H, W, 3) linear radiance image, camera exposure applied."""

    def light_group_images(self) -> dict[str, torch.Tensor]:
        """Light group name -> (H, W, 3) image of its lights; with `emission_image()` they sum to `render()`."""

    def emission_image(self) -> torch.Tensor:
        """(H, W, 3) the surfaces' own emission, no light's."""

    def edit_material(self, material: int | str, **values: object) -> None:
        """Set UsdPreviewSurface inputs (`PreviewSurfaceParams` field names, constants) of one
        material, by id or prim path (`material_edits.material_rows`).

        Raises:
            RelightError: `material_edits` is False.
        """

    def set_material_edits(self, edits: Mapping[int | str, Mapping[str, object]]) -> None:
        """Make the materials the baked ones with `edits` (material -> inputs, as `edit_material`
        takes them) and no others: what a session undoing and redoing material edits needs. Only
        what differs from the current materials is redone.

        Raises:
            RelightError: `material_edits` is False, or a bad material or input.
        """

    @property
    def edits(self) -> int:
        """Changes made so far to the rig (`set_light`, `remove_light`, `set_lights`) and the
        materials: progressive refinement starts again from a coarse frame when it grows."""

    def pending(self, stride: int | None) -> float:
        """The work `refine(stride)` would do, in light samples (a light at a shading point counts
        its samples): what progressive refinement predicts a frame's time from.

        Raises:
            RelightError: `progressive` is False.
        """

    def refine(self, stride: int | None) -> Refinement:
        """A frame of the current rig: exact where nothing changed since the last exact frame,
        the changed lights evaluated at one point per `stride` x `stride` pixels and upsampled
        elsewhere; `stride` None makes the exact frame, equal to `render()`. Work done for a
        coarse frame is kept (per light, per point) and never done again by a finer one or the
        exact one, unless an edit made it stale.

        Raises:
            RelightError: `progressive` is False.
        """

    def held_bytes(self) -> int:
        """Bytes of the work kept between renders (per-light transports, images, indirect light,
        kept grids), not counting the baked payloads loaded at open."""


@runtime_checkable
class GradientRelighter(CacheRelighter, Protocol):
    """A relighter that `relight solve` can differentiate in the light kinds it names.

    Attributes:
        gradient_kinds: the `--free` geometry kinds (`relight_torch.direct.gradients.GEOMETRY_KINDS`)
            whose gradients it provides; the solver refuses the others, naming the method. The
            direct Relighter provides them through `relight_torch.direct.gradients`, and the
            transfer relighter adds its indirect light's (the gathers' direct light differentiated
            the same way, carried by its linear transport).
    """

    gradient_kinds: frozenset[str]

    def scene_diagonal(self) -> float:
        """World length of the diagonal of the shaded points' bounding box (the solver's unit of
        position offsets)."""

    def freeze_light(self, light: Light, pose: LightPose, num_samples: int) -> object:
        """Trace the light's shadow rays at `pose` once, `num_samples` per point (no gradient):
        the visibility `differentiable_light_image` holds fixed."""

    def differentiable_light_image(self, light: Light, pose: LightPose, frozen: object) -> torch.Tensor:
        """(H, W, 3) image of the unit light (`direct.images.unit_light`) at `pose`, differentiable in
        the pose's tensors, visibility `frozen`; exposure applied as in `render`."""


@dataclass(frozen=True)
class Refinement:
    """One frame of progressive refinement (`CacheRelighter.refine`).

    Attributes:
        image: (H, W, 3) linear radiance image, camera exposure applied.
        evaluated: light evaluations (one light at one shading point) made for it.
        work: the light samples they evaluated (the units of `CacheRelighter.pending`).
        exact: whether `image` is the exact frame (`render()`).
    """

    image: torch.Tensor
    evaluated: int
    work: float
    exact: bool


def refuse_progressive(relighter: object) -> NoReturn:
    """The `pending` and `refine` of a relighter whose `progressive` is False.

    Raises:
        RelightError: always, naming the relighter's class.
    """
    raise RelightError(
        f"{type(relighter).__name__}: this cache's method has no progressive refinement (progressive is "
        f"False); render it whole"
    )


def refuse_material_edit(relighter: object) -> None:
    """The `edit_material` of a relighter whose `material_edits` is False.

    Raises:
        RelightError: always, naming the relighter's class.
    """
    raise RelightError(
        f"{type(relighter).__name__}: this cache's method bakes the materials into its light "
        f"transport; re-bake after a material edit (material_edits is False)"
    )


def tensor_bytes(*tensors: torch.Tensor | None) -> int:
    """Bytes of the given tensors (None counts 0)."""
    return sum(t.numel() * t.element_size() for t in tensors if t is not None)
