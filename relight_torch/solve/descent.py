"""Gradient descent on lights: what the closed form cannot solve (geometry, shaping, colour temperature).

The frame is modelled as

    image(theta) = rest + sum_i s_i(theta) (.) U_i(theta)

with `rest` and the unit images U_i of lights whose geometry is fixed taken from the relighter
(`linear.unit_images`), U_i of lights whose geometry is free from the differentiable direct
relighter: each step takes their value from the relighter at the current parameters and their
gradient from the relighter's differentiable twin (`protocol.GradientRelighter`, built on
`relight_torch.direct.gradients`: visibility traced at the current parameters and held fixed
through the gradient), and s_i the emission factor: the closed-form start times a free non-negative
multiple (per channel when colours are free) times blackbody(T) / blackbody(T_0).

Adam (Kingma & Ba 2015) runs on normalised unknowns z, so one learning rate fits all: position
offsets in units of the scene's diagonal (the G-buffer's bounding box), rotations in radians,
sizes as log(size / size_0), cone angle in units of 90 degrees, softness and focus as they are,
temperature in units of 1000 K, emission multiples as (multiple - 1). Limits are kept by
reparametrisation (sizes: the log) or by projection after each step (emission multiples >= 0,
cone angle in [0.5, 180] degrees, softness in [0, 1], focus >= 0, temperature in
`rig.TEMPERATURE_RANGE`). A step that raises the loss (the relighter's, with the visibility of
where the step landed) is refused and the step size halved, then grown back toward its schedule
by 1.5x per accepted step, so the descent is monotone in the true loss even where the frozen
visibility misleads a gradient (the Cornell box's ceiling light, 1 mm under the ceiling, is
pushed up by it while its x and z are wrong). The loss is the mask-weighted squared error over
the target's weighted energy plus `regularisation` x |z|^2, a pull toward the starting rig that
keeps lights the target says nothing about where they were.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from relight_torch.direct import gradients
from relight_torch.direct.gradients import LightPose, applies
from relight_torch.direct.relighter import colour_scale
from relight_torch.lights.emission import is_delta_light
from relight_torch.lights.light import Light
from relight_torch.protocol import CacheRelighter, GradientRelighter
from relight_torch.solve.linear import unit_images
from relight_torch.solve.rig import SCALE_KINDS, TEMPERATURE_RANGE, blackbody, blackbody_tensor, scaled_light

Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class DescentSettings:
    """The gradient solve's settings.

    Attributes:
        iterations: Adam steps at most.
        learning_rate: the first step size, in normalised units (module doc); it decays
            geometrically to `final_learning_rate` over `iterations`, and halves at each refused
            step (one that raised the loss).
        final_learning_rate: the last step size.
        regularisation: weight of the pull |z|^2 toward the starting rig against the relative
            squared error (1e-4: a 10 % move costs 1e-4 x 1, far below the error it explains).
        gradient_samples: light samples per shading point of the differentiable images (delta
            lights take one).
        tolerance: stop once the loss fell by less than this fraction over the last 20 accepted
            steps, or when refused steps have cut the step size below 1/1000 of the final one.
    """

    iterations: int = 200
    learning_rate: float = 0.03
    final_learning_rate: float = 0.002
    regularisation: float = 1e-4
    gradient_samples: int = 4
    tolerance: float = 1e-5


SHAPING_UNITS = (90.0, 1.0, 1.0)
"""The units of the shaping unknowns: cone angle (degrees), softness, focus."""


@dataclass
class _Unknowns:
    """One light's normalised unknowns (module doc); None where not free."""

    light: Light
    pose: LightPose | None  # the starting pose, when any geometry kind is free for this light
    kinds: tuple[str, ...]  # the geometry kinds free for this light
    multiple: torch.Tensor | None  # (3,) or (1,) emission multiple - 1
    temperature: torch.Tensor | None  # () (T - T_0) / 1000 K
    position: torch.Tensor | None = None
    rotation: torch.Tensor | None = None
    size: torch.Tensor | None = None
    shaping: torch.Tensor | None = None
    visibility: object | None = None  # the relighter's `freeze_light` at the current pose

    def tensors(self) -> list[torch.Tensor]:
        values = (self.multiple, self.temperature, self.position, self.rotation, self.size, self.shaping)
        return [t for t in values if t is not None]

    def current_pose(self, diagonal: float) -> LightPose:
        """The pose the unknowns stand for (tensors in the graph)."""
        start = self.pose
        assert start is not None, "only a light with free geometry has a pose"
        return LightPose(
            start.position + diagonal * self.position if self.position is not None else start.position,
            self.rotation if self.rotation is not None else start.rotation,
            start.size * torch.exp(self.size) if self.size is not None and start.size is not None else start.size,
            start.shaping + self.shaping * start.shaping.new_tensor(SHAPING_UNITS)
            if self.shaping is not None and start.shaping is not None
            else start.shaping,
        )

    def project(self) -> None:
        """Keep the limits (module doc) after a step."""
        with torch.no_grad():
            if self.multiple is not None:
                self.multiple.clamp_(min=-1.0)
            if self.temperature is not None:
                kelvin = self.light.color_temperature
                low, high = ((bound - kelvin) / 1000.0 for bound in TEMPERATURE_RANGE)
                self.temperature.clamp_(low, high)
            if self.shaping is not None and self.pose is not None and self.pose.shaping is not None:
                units = self.pose.shaping.new_tensor(SHAPING_UNITS)
                values = self.pose.shaping + self.shaping * units
                values = torch.stack((values[0].clamp(0.5, 180.0), values[1].clamp(0.0, 1.0), values[2].clamp_min(0.0)))
                self.shaping.copy_((values - self.pose.shaping) / units)


@dataclass(frozen=True)
class DescentResult:
    """The lights after descent, the loss before and after, the steps taken and the seconds."""

    lights: list[Light]
    loss_start: float
    loss_end: float
    iterations: int
    seconds: float


def descend(
    relighter: CacheRelighter,
    lights: Sequence[Light],
    rest: torch.Tensor,
    images: torch.Tensor,
    target: torch.Tensor,
    weights: torch.Tensor,
    free: Sequence[str],
    settings: DescentSettings = DescentSettings(),
    progress: Progress | None = None,
) -> DescentResult:
    """Solve the free kinds of `lights` by Adam through the relighter (module doc).

    Args:
        relighter: the relighter; a geometry kind needs its `gradient_kinds` (checked by the caller).
        lights: the solved lights at the start (the closed-form solution).
        rest: (H, W, 3) the frame without the solved lights; images: (L, H, W, 3) their unit images.
        target: (H, W, 3) linear target; weights: (H, W) non-negative pixel weights.
        free: the free kinds.
        progress: called with (step, iterations) after each step.
    """
    start_time = time.perf_counter()
    dtype = torch.float64
    rest, images, target = rest.to(dtype), images.to(dtype), target.to(dtype)
    weights = weights.to(dtype).unsqueeze(-1)
    energy = float((weights * target.square()).sum()) or 1.0
    diagonal = _scene_diagonal(relighter)
    device = rest.device
    unknowns = [_unknowns(light, free, dtype, device) for light in lights]
    parameters = [t for u in unknowns for t in u.tensors()]
    if not parameters:
        return DescentResult(list(lights), math.nan, math.nan, 0, 0.0)
    optimiser = torch.optim.Adam(parameters, lr=settings.learning_rate)
    decay = (settings.final_learning_rate / settings.learning_rate) ** (1.0 / max(settings.iterations, 1))
    starts = [torch.as_tensor(_factor(light), dtype=dtype, device=device) for light in lights]
    rate, best, kept = settings.learning_rate, math.inf, [t.detach().clone() for t in parameters]
    history: list[float] = []
    step = 0
    for step in range(1, settings.iterations + 1):
        # The moving lights' images at the current unknowns, from the relighter itself (the loss's
        # value is the relighter's), and their differentiable twins at frozen visibility (its gradient).
        exact = _moving_images(relighter, unknowns, diagonal, settings.gradient_samples)
        optimiser.zero_grad()
        frame = rest
        for index, (u, start) in enumerate(zip(unknowns, starts, strict=True)):
            image = images[index]
            if u.visibility is not None:
                assert isinstance(relighter, GradientRelighter)
                twin = relighter.differentiable_light_image(u.light, u.current_pose(diagonal), u.visibility).to(dtype)
                image = exact[u.light.path].to(dtype) + (twin - twin.detach())
            frame = frame + _scale(u, start) * image
        data = (weights * (frame - target).square()).sum() / energy
        pull = sum((t.square().sum() for t in parameters), torch.zeros((), dtype=dtype))
        loss = data + settings.regularisation * pull
        value = float(loss.detach())
        if progress is not None:
            progress(step, settings.iterations)
        if value > best:
            # The step made things worse, through what the frozen visibility could not see (a light
            # moved behind an occluder) or a step too long: back to the kept unknowns, half the step.
            _restore(parameters, kept)
            rate *= 0.5
            _set_rate(optimiser, rate)
            if rate < 1e-3 * settings.final_learning_rate:
                break
            continue
        best, kept = value, [t.detach().clone() for t in parameters]
        history.append(value)
        if len(history) > 20 and history[-21] - history[-1] < settings.tolerance * history[-21]:
            break
        loss.backward()
        optimiser.step()
        for u in unknowns:
            u.project()
        # Back toward the schedule after refused steps: one wall met need not slow every later step.
        rate = min(rate * 1.5, settings.learning_rate * decay**step)
        _set_rate(optimiser, rate)
    _restore(parameters, kept)  # the last step taken was never evaluated, or was refused
    solved = [_solved_light(u, start, diagonal, free) for u, start in zip(unknowns, starts, strict=True)]
    return DescentResult(solved, history[0], history[-1], step, time.perf_counter() - start_time)


def _restore(parameters: list[torch.Tensor], values: list[torch.Tensor]) -> None:
    with torch.no_grad():
        for parameter, value in zip(parameters, values, strict=True):
            parameter.copy_(value)


def _set_rate(optimiser: torch.optim.Optimizer, rate: float) -> None:
    for group in optimiser.param_groups:
        group["lr"] = rate


def _unknowns(light: Light, free: Sequence[str], dtype: torch.dtype, device: torch.device) -> _Unknowns:
    kinds = tuple(kind for kind in gradients.GEOMETRY_KINDS if kind in free and applies(kind, light))
    scale_free = [kind for kind in SCALE_KINDS if kind in free]
    multiple = None
    if scale_free:
        multiple = torch.zeros(3 if "color" in scale_free else 1, dtype=dtype, device=device, requires_grad=True)
    temperature = None
    if "temperature" in free and light.enable_color_temperature:
        temperature = torch.zeros((), dtype=dtype, device=device, requires_grad=True)
    pose = LightPose.of(light, dtype, device) if kinds else None
    u = _Unknowns(light, pose, kinds, multiple, temperature)
    if pose is not None:
        zeros = {
            "position": torch.zeros(3, dtype=dtype, device=device),
            "orientation": torch.zeros(3, dtype=dtype, device=device),
            "size": None if pose.size is None else torch.zeros_like(pose.size),
            "shaping": None if pose.shaping is None else torch.zeros_like(pose.shaping),
        }
        for kind in kinds:
            value = zeros[kind]
            if value is not None:
                setattr(u, "rotation" if kind == "orientation" else kind, value.requires_grad_(True))
    return u


def _moving_images(
    relighter: CacheRelighter, unknowns: list[_Unknowns], diagonal: float, samples: int
) -> dict[str, torch.Tensor]:
    """Put each moving light at its current pose on the relighter and return its unit image there
    (`linear.unit_images`); trace its differentiable twin's visibility there too (no gradient)."""
    moving = [u for u in unknowns if u.pose is not None]
    if not moving:
        return {}
    assert isinstance(relighter, GradientRelighter), "the solver refuses geometry kinds without gradients"
    for u in moving:
        pose = u.current_pose(diagonal)
        relighter.set_light(pose.posed_light(u.light))
        count = 1 if is_delta_light(u.light) else samples
        u.visibility = relighter.freeze_light(u.light, pose, count)
    _, images = unit_images(relighter, [u.light.path for u in moving])
    return {u.light.path: image for u, image in zip(moving, images, strict=True)}


def _factor(light: Light) -> np.ndarray:
    """(3,) the light's emission factor without its colour temperature's blackbody."""
    scale = colour_scale(light)
    if light.enable_color_temperature:
        scale = scale / blackbody(light.color_temperature)
    return scale


def _scale(u: _Unknowns, start: torch.Tensor) -> torch.Tensor:
    """(3,) the light's emission factor from its unknowns."""
    scale = start
    if u.multiple is not None:
        scale = scale * (1.0 + u.multiple)
    if u.light.enable_color_temperature:
        kelvin = torch.as_tensor(u.light.color_temperature, dtype=start.dtype, device=start.device)
        if u.temperature is not None:
            kelvin = kelvin + 1000.0 * u.temperature
        scale = scale * blackbody_tensor(kelvin)
    return scale


def _solved_light(u: _Unknowns, start: torch.Tensor, diagonal: float, free: Sequence[str]) -> Light:
    """The light the unknowns stand for, as plain numbers."""
    light = u.light
    if u.pose is not None:
        light = u.current_pose(diagonal).posed_light(light)
    if u.temperature is not None:
        kelvin = light.color_temperature + 1000.0 * float(u.temperature.detach())
        light = dataclasses.replace(light, color_temperature=kelvin)
    if u.multiple is not None:
        with torch.no_grad():
            scale = _scale(dataclasses.replace(u, light=light, temperature=None), start).cpu().numpy()
        light = scaled_light(light, scale, free)
    return light


def _scene_diagonal(relighter: CacheRelighter) -> float:
    """The unit of position offsets: the relighter's `scene_diagonal`, 1 for one without gradients
    (which moves no light)."""
    return relighter.scene_diagonal() if isinstance(relighter, GradientRelighter) else 1.0
