"""Gradient descent on lights: what the closed form cannot solve (geometry, shaping, colour temperature).

The frame is modelled as

    image(theta) = rest + sum_i s_i(theta) (.) U_i(theta)

with `rest` and the unit images U_i of lights whose geometry is fixed taken from the relighter
(`linear.unit_images`), U_i of lights whose geometry is free from the differentiable direct
relighter: each step takes their value from the relighter at the current parameters and their
derivatives from the relighter's differentiable twin (`protocol.GradientRelighter`, built on
`relight_torch.direct.gradients`: visibility traced at the current parameters and held fixed
through the derivative), and s_i the emission factor: the start (the closed form's, no dimmer
than the rig's for a light whose geometry is free: `solver._geometry_start`) times a free
non-negative multiple (per channel when colours are free) times blackbody(T) / blackbody(T_0).

The unknowns are few (a handful per light) and the residual is a whole image, so the solve is a
damped Gauss-Newton one, Levenberg-Marquardt (Levenberg 1944, Marquardt 1963): each step takes
the Jacobian of the weighted residual, one forward-mode derivative of the frame per unknown
(`torch.autograd.forward_ad`), and solves (J^T J + lambda diag(J^T J)) d = -J^T r. Unlike a
first-order method with one step size it scales each unknown by its own curvature: a narrow spot
light whose pool moves off a glossy floor within a few millimetres and a broad key light that
needs tens of centimetres take the steps each needs. The unknowns are normalised: position offsets
in units of the scene's diagonal (the G-buffer's bounding box), rotations in radians, sizes as
log(size / size_0), cone angle in units of 90 degrees, softness and focus as they are, temperature
in units of 1000 K, emission multiples as (multiple - 1). Limits are kept by reparametrisation
(sizes: the log) or by projection after each step (emission multiples >= 0, cone angle in
[0.5, 180] degrees, softness in [0, 1], focus >= 0, temperature in `rig.TEMPERATURE_RANGE`). A step
is taken only if it lowers the loss measured by the relighter with the visibility of where the step
lands, and lambda grows until one does, so the solve is monotone in the true loss even where the
frozen visibility misleads a derivative (the Cornell box's ceiling light, 1 mm under the ceiling,
is pushed up by it while its x and z are wrong). The loss is the mask-weighted squared error over
the target's weighted energy plus `regularisation` x |z|^2, a pull toward the starting rig that
keeps lights the target says nothing about where they were. With `robust`, the pixel weights are
Huber's (`linear.huber_weights`), refreshed from the residual at the start and after every
accepted step (iteratively reweighted least squares, Holland & Welsch 1977): a step is accepted
when it lowers the loss under the weights it was taken with.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.autograd.forward_ad as forward_ad

from relight_torch.direct import gradients
from relight_torch.direct.gradients import LightPose, applies
from relight_torch.direct.images import colour_scale
from relight_torch.lights.emission import is_delta_light
from relight_torch.lights.light import Light
from relight_torch.protocol import CacheRelighter, GradientRelighter
from relight_torch.solve.linear import huber_weights, unit_images
from relight_torch.solve.rig import SCALE_KINDS, TEMPERATURE_RANGE, blackbody, blackbody_tensor, scaled_light

Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class DescentSettings:
    """The gradient solve's settings.

    Attributes:
        iterations: evaluations of the loss at most (each a relighter render of the moving lights
            and, for an accepted step, one Jacobian).
        damping: the first Levenberg-Marquardt lambda, relative to the diagonal of J^T J; divided by 3
            after an accepted step, multiplied by 4 after a refused one.
        regularisation: weight of the pull |z|^2 toward the starting rig against the relative
            squared error (1e-4: a 10 % move costs 1e-4 x 1, far below the error it explains).
        gradient_samples: light samples per shading point of the differentiable images (delta
            lights take one).
        tolerance: stop once an accepted step lowers the loss by less than this fraction, or when
            lambda passes 1e10 (no step lowers it).
    """

    iterations: int = 60
    damping: float = 1e-3
    regularisation: float = 1e-4
    gradient_samples: int = 4
    tolerance: float = 1e-5


SHAPING_UNITS = (90.0, 1.0, 1.0)
"""The units of the shaping unknowns: cone angle (degrees), softness, focus."""

_UNKNOWN_FIELDS = ("multiple", "temperature", "position", "rotation", "size", "shaping")
_GEOMETRY_FIELDS = frozenset(("position", "rotation", "size", "shaping"))


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

    def fields(self) -> list[str]:
        """The names of the unknowns that are free, in a fixed order."""
        return [name for name in _UNKNOWN_FIELDS if getattr(self, name) is not None]

    def tensors(self) -> list[torch.Tensor]:
        return [getattr(self, name) for name in self.fields()]

    def current_pose(self, diagonal: float) -> LightPose:
        """The pose the unknowns stand for."""
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
    """The lights after descent, the loss before and after, the steps taken, the seconds, and
    what the target could not determine at the solution (`unresolved`)."""

    lights: list[Light]
    loss_start: float
    loss_end: float
    iterations: int
    seconds: float
    unresolved: tuple[str, ...] = ()


RIDGE_CURVATURE = 1e-3
"""A combination of unknowns whose curvature of the loss is below this fraction of the single
unknowns' (the normalised J^T J's smallest eigenvalues) is one the target cannot pin down."""
RIDGE_SHARE = 0.3
"""The unknowns named for a ridge: those with at least this component in its direction."""
_ELEMENT_NAMES = {
    "position": ("x", "y", "z"),
    "rotation": ("x", "y", "z"),
    "shaping": ("cone angle", "cone softness", "focus"),
}


def unresolved(jacobian: torch.Tensor, labels: Sequence[str]) -> list[str]:
    """What a least-squares solution cannot determine, from the Jacobian (M, n) of its residual in
    n unknowns named by `labels`: one line per unknown the residual does not depend on, and per
    ridge, a combination of unknowns along which the loss curves less than RIDGE_CURVATURE
    times as much as along any one of them (its Gauss-Newton curvature, the eigenvalues of J^T J
    with each unknown scaled to unit curvature). On a ridge the data only fix a trade-off (a
    light further away and brighter): the solve's answer along it follows the start and the
    pull toward it, not the target."""
    normal = jacobian.T @ jacobian
    scale = torch.diagonal(normal).sqrt()
    seen = scale > 1e-12 * float(scale.max().clamp_min(1e-300))
    blind = zip(labels, seen.tolist(), strict=True)
    lines = [f"{label}: the target does not depend on it" for label, ok in blind if not ok]
    index = torch.nonzero(seen).squeeze(-1)
    if index.numel() < 2:
        return lines
    kept = normal.index_select(0, index).index_select(1, index) / torch.outer(scale[index], scale[index])
    values, vectors = torch.linalg.eigh(kept)
    for value, vector in zip(values.tolist(), vectors.T, strict=True):
        if value >= RIDGE_CURVATURE:
            break
        names = [labels[int(index[k])] for k in torch.nonzero(vector.abs() >= RIDGE_SHARE).squeeze(-1).tolist()]
        lines.append(
            f"{' and '.join(names)}: the target fixes only a trade-off between them "
            f"(curvature {value:.1e} of theirs alone); the solved values along it follow the start"
        )
    return lines


def faded(start: torch.Tensor, jacobian: torch.Tensor, labels: Sequence[str], owners: Sequence[str]) -> list[str]:
    """The unknowns the target stopped determining on the way: one line per light (`owners` (n,)
    gives each unknown's light) naming its unknowns whose curvature of the loss, diag(J^T J) of the
    Jacobian (M, n) at the solution, fell below RIDGE_CURVATURE times `start` (n,), the same at the
    start, and is not zero (`unresolved` names those).

    An unknown of a light is seen through that light's image, so its curvature falls with the
    light's emission squared and with the share of its light the camera sees: a solve that turned a
    light off, or moved it out of view, leaves its geometry wherever the last step put it. Typically
    the target shows the light where no local step reaches: moved behind an occluder, its image at
    every nearby position is the wrong one (visibility has no gradient), and the best the solve
    can do is switch it off. Compared with the start rather than with the other unknowns (as
    `unresolved` does) so that a light the rig has dim is not flagged for being dim."""
    end = jacobian.square().sum(0)
    scale = float(end.sqrt().max().clamp_min(1e-300))
    lost = (end < RIDGE_CURVATURE * start) & (end.sqrt() > 1e-12 * scale)
    lines = []
    for owner in dict.fromkeys(owners):
        index = [k for k, name in enumerate(owners) if name == owner and bool(lost[k])]
        if not index:
            continue
        names = [labels[k].removeprefix(f"{owner} ") for k in index]
        ratio = max(float(end[k] / start[k]) for k in index)
        lines.append(
            f"{owner} {', '.join(names)}: the solve turned the light off or out of view (curvature "
            f"{ratio:.1e} of the start's), so the target no longer determines them; if the target shows "
            "it elsewhere, it may lie behind an occluder, where no local step follows it"
        )
    return lines


def _labels(unknowns: list[_Unknowns]) -> list[str]:
    """One label per unknown, in the Jacobian's column order (`_jacobian`)."""
    labels = []
    for u in unknowns:
        for name in u.fields():
            count = getattr(u, name).numel()
            if name == "multiple":
                parts = ("red", "green", "blue") if count == 3 else ("",)
                labels += [f"{u.light.path} intensity" + (f" ({part})" if part else "") for part in parts]
            elif name in _ELEMENT_NAMES:
                labels += [f"{u.light.path} {name} {part}" for part in _ELEMENT_NAMES[name][:count]]
            elif count == 1:
                labels.append(f"{u.light.path} {name}")
            else:
                labels += [f"{u.light.path} {name} {k}" for k in range(count)]
    return labels


@dataclass(frozen=True)
class _Problem:
    """What every evaluation of the model shares (`descend`'s arguments, in float64)."""

    relighter: CacheRelighter
    rest: torch.Tensor  # (H, W, 3)
    images: torch.Tensor  # (L, H, W, 3)
    target: torch.Tensor  # (H, W, 3)
    root_weights: torch.Tensor  # (H, W, 1) sqrt(weight / target energy), the weight Huber's with `robust`
    mask: torch.Tensor  # (H, W) the caller's pixel weights
    energy: float  # sum of mask x |target|^2
    starts: list[torch.Tensor]  # (3,) each light's emission factor at the start, no blackbody
    diagonal: float
    samples: int


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
    robust: bool = False,
) -> DescentResult:
    """Solve the free kinds of `lights` by Levenberg-Marquardt through the relighter (module doc).

    Args:
        relighter: the relighter; a geometry kind needs its `gradient_kinds` (checked by the caller).
        lights: the solved lights at the start (the closed-form solution).
        rest: (H, W, 3) the frame without the solved lights; images: (L, H, W, 3) their unit images.
        target: (H, W, 3) linear target; weights: (H, W) non-negative pixel weights.
        free: the free kinds.
        progress: called with (evaluation, iterations) after each evaluation of the loss.
        robust: Huber's loss instead of the squared error (module doc); the result's losses are
            then under the weights of the step they were measured at.
    """
    start_time = time.perf_counter()
    dtype = torch.float64
    device = rest.device
    target = target.to(dtype)
    energy = float((weights.to(dtype) * target.square().sum(-1)).sum()) or 1.0
    problem = _Problem(
        relighter,
        rest.to(dtype),
        images.to(dtype),
        target,
        torch.sqrt(weights.to(dtype) / energy).unsqueeze(-1),
        weights.to(dtype),
        energy,
        [torch.as_tensor(_factor(light), dtype=dtype, device=device) for light in lights],
        _scene_diagonal(relighter),
        settings.gradient_samples,
    )
    unknowns = [_unknowns(light, free, dtype, device) for light in lights]
    if not any(u.tensors() for u in unknowns):
        return DescentResult(list(lights), math.nan, math.nan, 0, 0.0)
    loss, exact, residual = _evaluate(problem, unknowns, settings.regularisation)
    if robust:
        problem, loss, residual = _reweight(problem, unknowns, residual, settings.regularisation)
    history, damping, evaluations = [loss], settings.damping, 1
    current = True  # the relighter and the frozen visibility stand at the unknowns' values
    start_curvature: torch.Tensor | None = None  # diag(J^T J) at the start (`faded`)
    while evaluations < settings.iterations and damping < 1e10:
        jacobian = _jacobian(problem, unknowns, exact)
        if start_curvature is None:
            start_curvature = jacobian.square().sum(0)
        kept = [t.clone() for u in unknowns for t in u.tensors()]
        z = torch.cat([t.reshape(-1) for t in kept])
        normal = jacobian.T @ jacobian + settings.regularisation * torch.eye(z.shape[0], dtype=dtype, device=device)
        gradient = jacobian.T @ residual + settings.regularisation * z
        while evaluations < settings.iterations and damping < 1e10:
            damped = normal + damping * torch.diag(torch.diagonal(normal).clamp_min(1e-12))
            # Least squares rather than a solve: an unknown the target cannot see has a zero column.
            _assign(unknowns, z - torch.linalg.lstsq(damped, gradient.unsqueeze(1)).solution.squeeze(1))
            tried, tried_exact, tried_residual = _evaluate(problem, unknowns, settings.regularisation)
            evaluations, current = evaluations + 1, True
            if progress is not None:
                progress(evaluations, settings.iterations)
            if tried < loss:
                damping = max(damping / 3.0, 1e-9)
                break
            # Worse, through what the frozen visibility could not see (a light moved behind an
            # occluder) or a step past where the linear model holds: back, and a shorter step.
            _restore(unknowns, kept)
            damping, current = damping * 4.0, False
        else:
            break
        improvement = (loss - tried) / loss
        loss, exact, residual = tried, tried_exact, tried_residual
        history.append(loss)
        if improvement < settings.tolerance:
            break
        if robust:
            problem, loss, residual = _reweight(problem, unknowns, residual, settings.regularisation)
    # What the target leaves open, at the solution: evaluated there again when a refused last step
    # left the relighter and the frozen visibility where it tried.
    if not current:
        _, exact, _ = _evaluate(problem, unknowns, settings.regularisation)
    jacobian, labels = _jacobian(problem, unknowns, exact), _labels(unknowns)
    lines = unresolved(jacobian, labels)
    if start_curvature is not None:
        owners = [u.light.path for u in unknowns for t in u.tensors() for _ in range(t.numel())]
        lines += faded(start_curvature, jacobian, labels, owners)
    solved = [
        _solved_light(u, start, problem.diagonal, free) for u, start in zip(unknowns, problem.starts, strict=True)
    ]
    seconds = time.perf_counter() - start_time
    return DescentResult(solved, history[0], history[-1], len(history) - 1, seconds, tuple(lines))


def _evaluate(
    problem: _Problem, unknowns: list[_Unknowns], regularisation: float
) -> tuple[float, dict[str, torch.Tensor], torch.Tensor]:
    """The loss at the unknowns' values (the relighter's images of the moving lights there, their
    visibility frozen there for the next Jacobian), those images and the (M,) weighted residual."""
    exact = _moving_images(problem.relighter, unknowns, problem.diagonal, problem.samples)
    with torch.no_grad():
        residual = (problem.root_weights * (_frame(problem, unknowns, exact, None) - problem.target)).reshape(-1)
        return float(residual.square().sum() + regularisation * _pull(unknowns, residual.dtype)), exact, residual


def _reweight(
    problem: _Problem, unknowns: list[_Unknowns], residual: torch.Tensor, regularisation: float
) -> tuple[_Problem, float, torch.Tensor]:
    """Huber's weights from the (M,) weighted residual at the unknowns' values: the problem with
    them, and the loss and weighted residual there under them (no new render)."""
    root = problem.root_weights
    difference = residual.reshape(problem.target.shape) / root.clamp_min(1e-300)  # 0 where the weight is
    root = torch.sqrt(huber_weights(difference, problem.mask, problem.target) / problem.energy).unsqueeze(-1)
    residual = (root * difference).reshape(-1)
    loss = float(residual.square().sum()) + regularisation * float(_pull(unknowns, residual.dtype))
    return dataclasses.replace(problem, root_weights=root), loss, residual


def _pull(unknowns: list[_Unknowns], dtype: torch.dtype) -> torch.Tensor:
    """|z|^2 of the normalised unknowns (module doc)."""
    return sum((t.square().sum() for u in unknowns for t in u.tensors()), torch.zeros((), dtype=dtype))


def _jacobian(problem: _Problem, unknowns: list[_Unknowns], exact: dict[str, torch.Tensor]) -> torch.Tensor:
    """(M, n) the weighted residual's Jacobian in the n unknowns (flattened in `_Unknowns.fields`
    order, light by light), one forward-mode derivative per unknown."""
    columns = []
    for index, u in enumerate(unknowns):
        for name in u.fields():
            value = getattr(u, name)
            twin = index if name in _GEOMETRY_FIELDS else None
            for element in range(value.numel()):
                direction = torch.zeros_like(value).reshape(-1)
                direction[element] = 1.0
                with forward_ad.dual_level():
                    dual = forward_ad.make_dual(value, direction.reshape(value.shape))
                    moved = list(unknowns)
                    moved[index] = dataclasses.replace(u, **{name: dual})
                    frame = _frame(problem, moved, exact, twin)
                    tangent = forward_ad.unpack_dual(frame).tangent
                columns.append((problem.root_weights * tangent).reshape(-1))
    return torch.stack(columns, dim=1)


def _frame(
    problem: _Problem, unknowns: list[_Unknowns], exact: dict[str, torch.Tensor], twin: int | None
) -> torch.Tensor:
    """(H, W, 3) the model frame (module doc). The relighter's exact images carry the values; light
    `twin`'s differentiable image adds its derivative in the pose (value zero: twin - twin)."""
    frame = problem.rest
    for index, (u, start) in enumerate(zip(unknowns, problem.starts, strict=True)):
        image = problem.images[index]
        if u.visibility is not None:
            image = exact[u.light.path].to(frame.dtype)
            if index == twin:
                relighter = problem.relighter
                assert isinstance(relighter, GradientRelighter)
                moved = relighter.differentiable_light_image(u.light, u.current_pose(problem.diagonal), u.visibility)
                image = image + (moved - moved.detach()).to(frame.dtype)
        frame = frame + _scale(u, start) * image
    return frame


def _assign(unknowns: list[_Unknowns], z: torch.Tensor) -> None:
    """Set the unknowns from the flat vector z and keep their limits."""
    offset = 0
    for u in unknowns:
        for t in u.tensors():
            t.copy_(z[offset : offset + t.numel()].reshape(t.shape))
            offset += t.numel()
        u.project()


def _restore(unknowns: list[_Unknowns], values: list[torch.Tensor]) -> None:
    """Set the unknowns (flattened light by light, as `_Unknowns.tensors`) to `values`."""
    tensors = [t for u in unknowns for t in u.tensors()]
    for tensor, value in zip(tensors, values, strict=True):
        tensor.copy_(value)


def _unknowns(light: Light, free: Sequence[str], dtype: torch.dtype, device: torch.device) -> _Unknowns:
    kinds = tuple(kind for kind in gradients.GEOMETRY_KINDS if kind in free and applies(kind, light))
    scale_free = [kind for kind in SCALE_KINDS if kind in free]
    multiple = None
    if scale_free:
        multiple = torch.zeros(3 if "color" in scale_free else 1, dtype=dtype, device=device)
    temperature = None
    if "temperature" in free and light.enable_color_temperature:
        temperature = torch.zeros((), dtype=dtype, device=device)
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
                setattr(u, "rotation" if kind == "orientation" else kind, value)
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
