"""`solve_lights`: light settings that make a relighter's frame look like a target image.

Two stages (docs/SOLVE.md):

1. intensities and colours in closed form (`linear`: non-negative least squares of per-light
   images, Schoeneman et al. 1993), through any relighter;
2. if position, orientation, size, shaping or colour temperature are free, gradient descent from
   that start (`descent`), through a relighter that differentiates the geometry kinds
   (`protocol.GradientRelighter`); then, when intensities or colours are free, the closed form
   again at the solved geometry, so that they are the relighter's exact optimum there.

With `robust`, both stages fit under Huber's loss instead of the squared error (`linear`'s module
doc): for targets made by another renderer or a camera, whose disagreement with the relighter at
a few pixels would otherwise decide the solve.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from relight_torch.direct.gradients import GEOMETRY_KINDS, applies
from relight_torch.direct.images import colour_scale
from relight_torch.errors import RelightError
from relight_torch.lights.light import Light
from relight_torch.protocol import CacheRelighter, GradientRelighter
from relight_torch.solve.descent import DescentSettings, Progress, descend
from relight_torch.solve.linear import current_scales, robust_scales, solve_scales, unit_images
from relight_torch.solve.rig import SCALE_KINDS, parse_free, scaled_light


@dataclass(frozen=True)
class SolveResult:
    """What `solve_lights` found.

    Attributes:
        before, after: the whole rig before and after (lights matched by path).
        solved: the prim paths of the solved lights.
        loss_start, loss_end: the mask-weighted relative squared error sum w |image - target|^2 /
            sum w |target|^2 of the relighter's frame under `before` and `after`.
        iterations: gradient steps taken (0 for the closed form alone).
        seconds: wall time of the whole solve.
        unresolved: one line per unknown or combination of unknowns of the gradient solve that
            the target does not determine (`descent.unresolved`).
    """

    before: list[Light]
    after: list[Light]
    solved: tuple[str, ...]
    loss_start: float
    loss_end: float
    iterations: int
    seconds: float
    unresolved: tuple[str, ...] = ()


def solve_lights(
    relighter: CacheRelighter,
    target: torch.Tensor | np.ndarray,
    mask: torch.Tensor | np.ndarray | None = None,
    solve: Sequence[str] | None = None,
    free: str | Sequence[str] = ("intensity", "color"),
    settings: DescentSettings = DescentSettings(),
    progress: Progress | None = None,
    robust: bool = False,
) -> SolveResult:
    """Solve the `free` inputs of the lights `solve` so that `relighter.render()` matches `target`.

    The relighter is left holding the solved rig.

    Args:
        relighter: any relighter (`relight_torch.open_cache`); geometry kinds need one that
            differentiates them (its `gradient_kinds`).
        target: (H, W, 3) linear image of the relighter's size (camera exposure applied, like `render`).
        mask: (H, W) non-negative pixel weights, or None for all pixels alike.
        solve: prim paths of the lights to solve; None for every light of the rig.
        free: kinds from `rig.FREE_KINDS`, as a list or 'intensity,color'.
        settings: the gradient solve's settings.
        progress: called with (step, iterations) during the gradient solve.
        robust: fit under Huber's loss (module doc); `loss_start` and `loss_end` stay the squared
            error.

    Raises:
        RelightError: a bad target or mask shape, an unknown light or kind, or a kind the
            relighter's method cannot differentiate (one line each).
    """
    start_time = time.perf_counter()
    kinds = parse_free(free)
    before = relighter.lights
    frame = relighter.render()
    target_t = _image(target, frame, "target")
    weights = _weights(mask, frame)
    paths = _solved_paths(before, solve)
    _check_gradients(relighter, kinds, [light for light in before if light.path in paths])
    loss_start = _loss(frame, target_t, weights)

    rest, images = unit_images(relighter, paths)
    by_path = {light.path: light for light in before}
    solved = [by_path[path] for path in paths]
    scale_kinds = [kind for kind in SCALE_KINDS if kind in kinds]
    if scale_kinds:
        solved = _closed_form(solved, rest, images, target_t, weights, kinds, robust)
    iterations = 0
    lines: tuple[str, ...] = ()
    if any(kind in kinds for kind in GEOMETRY_KINDS + ("temperature",)):
        solved = [_geometry_start(light, by_path[light.path], kinds) for light in solved]
        result = descend(relighter, solved, rest, images, target_t, weights, kinds, settings, progress, robust)
        solved, iterations, lines = result.lights, result.iterations, result.unresolved
        if scale_kinds:  # the closed form again, now through the relighter at the solved geometry
            _set(relighter, before, solved)
            rest, images = unit_images(relighter, paths)
            solved = _closed_form(solved, rest, images, target_t, weights, kinds, robust)
    after = _set(relighter, before, solved)
    loss_end = _loss(relighter.render(), target_t, weights)
    seconds = time.perf_counter() - start_time
    return SolveResult(before, after, tuple(paths), loss_start, loss_end, iterations, seconds, lines)


def _closed_form(
    lights: list[Light],
    rest: torch.Tensor,
    images: torch.Tensor,
    target: torch.Tensor,
    weights: torch.Tensor,
    kinds: Sequence[str],
    robust: bool,
) -> list[Light]:
    current = current_scales(lights)
    residual = target - rest.to(target.dtype)
    if robust:
        factors, _ = robust_scales(images, residual, weights, current, "color" in kinds, target)
    else:
        factors = solve_scales(images, residual, weights, current, "color" in kinds)
    return [scaled_light(light, factor, kinds) for light, factor in zip(lights, factors, strict=True)]


def _geometry_start(closed: Light, rig: Light, kinds: Sequence[str]) -> Light:
    """Where the descent starts a light: the closed form's emission, but no dimmer than the rig's
    for a light whose geometry is free.

    The closed form fits the emission at the starting geometry. A light the target shows elsewhere
    (a spot whose pool has moved) can fit there with almost none, and a light that is off has no
    gradient in its geometry; the descent's emission unknown multiplies the start, and its pull
    toward the start costs (multiple - 1)^2, so it cannot bring the light back either (the test
    `test_descent_starts_a_movable_light_at_its_rig_emission`). Started at the rig's emission, the
    descent sees where the light's image should go, and solves its brightness with it.
    """
    if not any(kind in kinds and applies(kind, rig) for kind in GEOMETRY_KINDS):
        return closed
    return closed if float(colour_scale(closed).max()) >= float(colour_scale(rig).max()) else rig


def _set(relighter: CacheRelighter, rig: list[Light], solved: list[Light]) -> list[Light]:
    """Put the solved lights into the rig (same order) on the relighter; the new rig."""
    by_path = {light.path: light for light in solved}
    lights = [by_path.get(light.path, light) for light in rig]
    relighter.set_lights(lights)
    return lights


def _loss(image: torch.Tensor, target: torch.Tensor, weights: torch.Tensor) -> float:
    w = weights.to(torch.float64).unsqueeze(-1)
    energy = float((w * target.to(torch.float64).square()).sum()) or 1.0
    return float((w * (image.to(torch.float64) - target.to(torch.float64)).square()).sum()) / energy


def _image(value: torch.Tensor | np.ndarray, like: torch.Tensor, name: str) -> torch.Tensor:
    image = torch.as_tensor(np.asarray(value) if not torch.is_tensor(value) else value)
    if image.ndim == 3 and image.shape[-1] > 3:
        image = image[..., :3]  # alpha is not light
    height, width = like.shape[:2]
    if image.ndim != 3 or image.shape[-1] != 3:
        raise RelightError(f"{name}: expected an RGB image, got shape {tuple(image.shape)}")
    if tuple(image.shape[:2]) != (height, width):
        raise RelightError(
            f"{name}: {image.shape[1]}x{image.shape[0]} image, but the cache renders {width}x{height} "
            "(render the target at the cache's resolution)"
        )
    if not bool(torch.isfinite(image).all()):
        raise RelightError(f"{name}: has non-finite pixels")
    return image.to(like.device, torch.float64)


def _weights(mask: torch.Tensor | np.ndarray | None, like: torch.Tensor) -> torch.Tensor:
    height, width = like.shape[:2]
    if mask is None:
        return torch.ones(height, width, dtype=torch.float64, device=like.device)
    weights = torch.as_tensor(np.asarray(mask) if not torch.is_tensor(mask) else mask).to(torch.float64)
    if weights.ndim == 3:
        weights = weights[..., :3].mean(-1)  # a grey mask saved as RGB
    if tuple(weights.shape) != (height, width):
        raise RelightError(
            f"mask: {tuple(weights.shape)} pixels, but the cache renders {width}x{height} "
            f"(expected ({height}, {width}))"
        )
    if not bool(torch.isfinite(weights).all()) or bool((weights < 0).any()) or not bool((weights > 0).any()):
        raise RelightError("mask: weights must be finite, non-negative and not all zero")
    return weights.to(like.device)


def _solved_paths(rig: list[Light], solve: Sequence[str] | None) -> list[str]:
    paths = [light.path for light in rig]
    if not paths or (solve is not None and not solve):
        raise RelightError("--solve: no light to solve (the rig has none, or none was named)")
    if solve is None:
        return paths
    for path in solve:
        if path not in paths:
            raise RelightError(f"--solve {path}: no such light in the rig (lights: {', '.join(paths) or 'none'})")
    return [path for path in paths if path in set(solve)]


def _check_gradients(relighter: CacheRelighter, kinds: Sequence[str], lights: list[Light]) -> None:
    """Refuse a geometry kind the relighter cannot differentiate, or that no solved light has."""
    supported = relighter.gradient_kinds if isinstance(relighter, GradientRelighter) else frozenset()
    for kind in kinds:
        if kind not in GEOMETRY_KINDS:
            continue
        if kind not in supported:
            method = _method_name(relighter)
            raise RelightError(
                f"--free {kind}: the {method} method's relighter has no gradients for {kind} "
                "(solve it on a direct or transfer cache, or free only intensity,exposure,color,temperature)"
            )
        if not any(applies(kind, light) for light in lights):
            raise RelightError(f"--free {kind}: none of the solved lights has a {kind} to solve")
    if "temperature" in kinds and not any(light.enable_color_temperature for light in lights):
        raise RelightError("--free temperature: none of the solved lights enables its colour temperature")


def _method_name(relighter: object) -> str:
    """The cache method of a relighter (its layer's description, or its direct relighter's)."""
    for holder in (relighter, getattr(relighter, "direct", None)):
        description = getattr(holder, "description", None)
        if description is not None:
            return str(description.method)
    return type(relighter).__name__
