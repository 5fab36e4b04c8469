"""What `relight solve` may free, and how a solved emission scale is written back as UsdLux inputs.

A light's emission enters its image through one (3,) factor (`direct.images.colour_scale`):

    scale = intensity * 2^exposure * color [* blackbody(colorTemperature)]

so the linear solve finds scales, and this module splits a scale into the inputs the user freed:
the colour keeps the starting colour's largest component (white stays max 1) and the intensity
(or, with exposure freed and intensity not, the exposure) carries the rest.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable

import numpy as np
import torch
from pxr import UsdLux

from relight_torch.direct.gradients import GEOMETRY_KINDS
from relight_torch.errors import RelightError
from relight_torch.lights.light import Light

COLOUR_KINDS = ("intensity", "exposure", "color", "temperature")
"""Free kinds that change only a light's emission factor: linear in the image, every method solves them."""
FREE_KINDS = COLOUR_KINDS + GEOMETRY_KINDS
"""Every `--free` kind, in the order the help lists them."""
SCALE_KINDS = ("intensity", "exposure", "color")
"""The kinds the closed-form non-negative least squares solves."""

MIN_EXPOSURE = -64.0
"""The exposure written for a light the solve turns off when only its exposure is free (2^-64 ~ 0)."""
TEMPERATURE_RANGE = (1000.0, 10000.0)
"""Kelvin range `colorTemperature` is projected into (UsdLux's blackbody table spans it)."""


def parse_free(text: str | Iterable[str]) -> tuple[str, ...]:
    """Free kinds from 'intensity,color' (or a list of names), checked, in FREE_KINDS order.

    Raises:
        RelightError: an unknown kind, or none.
    """
    names = [name.strip() for name in (text.split(",") if isinstance(text, str) else text) if name.strip()]
    unknown = [name for name in names if name not in FREE_KINDS]
    if unknown:
        raise RelightError(f"--free {unknown[0]}: unknown kind (expected some of {','.join(FREE_KINDS)})")
    if not names:
        raise RelightError(f"--free: no kind given (expected some of {','.join(FREE_KINDS)})")
    return tuple(kind for kind in FREE_KINDS if kind in names)


def blackbody(temperature: float) -> np.ndarray:
    """(3,) float64 `UsdLux.BlackbodyTemperatureAsRgb`, the one colour-temperature function."""
    return np.asarray(UsdLux.BlackbodyTemperatureAsRgb(float(temperature)), np.float64)


class _Blackbody(torch.autograd.Function):
    """UsdLux's blackbody colour of a 0-d temperature tensor, differentiated (reverse and forward
    mode) by central differences of the same function (1 K steps: its table is smooth on that scale)."""

    @staticmethod
    def forward(ctx, temperature: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(temperature)
        ctx.save_for_forward(temperature)
        return temperature.new_tensor(blackbody(float(temperature)))

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        (temperature,) = ctx.saved_tensors
        return (grad * _blackbody_slope(temperature)).sum()

    @staticmethod
    def jvp(ctx, tangent: torch.Tensor) -> torch.Tensor:
        (temperature,) = ctx.saved_tensors
        return tangent * _blackbody_slope(temperature)


def _blackbody_slope(temperature: torch.Tensor) -> torch.Tensor:
    """(3,) d blackbody / d kelvin at a 0-d temperature, by central differences."""
    kelvin = float(temperature)
    return temperature.new_tensor((blackbody(kelvin + 1.0) - blackbody(kelvin - 1.0)) / 2.0)


def blackbody_tensor(temperature: torch.Tensor) -> torch.Tensor:
    """(3,) blackbody colour of a 0-d temperature tensor in kelvin, differentiable."""
    result: torch.Tensor = _Blackbody.apply(temperature)
    return result


def scaled_light(light: Light, scale: np.ndarray, free: Iterable[str]) -> Light:
    """`light` with the inputs in `free` set so that its emission factor is `scale`.

    Args:
        light: the light before (its colour temperature and any input not freed are kept).
        scale: (3,) the wanted emission factor (`direct.images.colour_scale`), non-negative; with
            'color' not free, a multiple of the light's current factor.
        free: the free kinds; 'intensity', 'exposure' and 'color' are read.

    Returns:
        The light; with 'color' free the colour keeps the starting colour's largest component
        (1 when it was black) and intensity (or else exposure) carries the brightness.
    """
    free = set(free)
    scale = np.maximum(np.asarray(scale, np.float64), 0.0)
    temperature = blackbody(light.color_temperature) if light.enable_color_temperature else np.ones(3)
    gain = 2.0**light.exposure * temperature
    base = light.intensity * gain
    if "color" not in free:  # a multiple k of the current factor
        current = base * np.asarray(light.color, np.float64)
        k = float(np.max(scale) / np.max(current)) if np.max(current) > 0 else 0.0
        if "intensity" in free:
            return dataclasses.replace(light, intensity=light.intensity * k)
        return dataclasses.replace(light, exposure=_exposure(light.exposure, k))
    per_channel = np.divide(scale, gain, out=np.zeros(3), where=gain > 0)  # intensity x color
    peak = float(per_channel.max())
    reference = max(float(np.max(light.color)), 0.0) or 1.0
    if "intensity" not in free and "exposure" not in free:
        color = per_channel / light.intensity if light.intensity > 0 else np.asarray(light.color)
        return dataclasses.replace(light, color=_colour(color))
    if peak == 0.0:  # the target wants the light off: keep its colour, zero its brightness
        if "intensity" in free:
            return dataclasses.replace(light, intensity=0.0)
        return dataclasses.replace(light, exposure=MIN_EXPOSURE)
    color = _colour(per_channel * (reference / peak))
    if "intensity" in free:
        return dataclasses.replace(light, intensity=peak / reference, color=color)
    ratio = peak / reference / light.intensity if light.intensity > 0 else 0.0
    return dataclasses.replace(light, color=color, exposure=_exposure(light.exposure, ratio))


def _exposure(exposure: float, factor: float) -> float:
    return max(exposure + math.log2(factor), MIN_EXPOSURE) if factor > 0 else MIN_EXPOSURE


def _colour(values: np.ndarray) -> tuple[float, float, float]:
    return (float(values[0]), float(values[1]), float(values[2]))
