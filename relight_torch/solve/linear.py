"""Closed-form intensities and colours: non-negative least squares of per-light images.

Light transport is linear in each light's emission (Schoeneman, Dorsey, Smits, Arvo & Greenberg
1993, "Painting with Light"): with U_i the image of light i at unit emission and F the rest of the
frame (the other lights and the surfaces' own emission), the frame under emission factors x_i is

    image = F + sum_i x_i (.) U_i           (x_i per channel, or a scalar times the current colour)

for every relighting method, indirect light included, so the factors nearest a target in the
mask-weighted least-squares sense are a non-negative least-squares problem per channel. The
images come from the relighter through the `CacheRelighter` protocol alone.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import torch
from scipy.optimize import nnls

from relight_torch.direct.images import colour_scale, unit_light
from relight_torch.errors import RelightError
from relight_torch.lights.light import Light
from relight_torch.protocol import CacheRelighter

_GROUP = "relightSolve{}"  # light groups given to the solved lights while their images are taken


def unit_images(relighter: CacheRelighter, paths: Sequence[str]) -> tuple[torch.Tensor, torch.Tensor]:
    """The images of lights `paths` at unit emission, and the rest of the frame.

    Each solved light is set to its `unit_light` in a light group of its own and the groups' images
    (`light_group_images`, direct and indirect layers summed) are read; the rig is restored after.

    Returns:
        (rest (H, W, 3), images (L, H, W, 3)): `render()` of the unit rig is rest + images.sum(0).

    Raises:
        RelightError: a light group of the rig already has one of the names used here.
    """
    rig = relighter.lights
    by_path = {light.path: light for light in rig}
    groups = [_GROUP.format(index) for index in range(len(paths))]
    taken = {light.light_group for light in rig} & set(groups)
    if taken:
        raise RelightError(f"light group {sorted(taken)[0]!r} is reserved by relight solve; rename it")
    try:
        for path, group in zip(paths, groups, strict=True):
            relighter.set_light(dataclasses.replace(unit_light(by_path[path]), light_group=group))
        layers = relighter.light_group_images()
        images = torch.stack([_group_image(layers, group) for group in groups])
        rest = relighter.render() - images.sum(0)
    finally:
        relighter.set_lights(rig)
    return rest, images


def _group_image(layers: dict[str, torch.Tensor], group: str) -> torch.Tensor:
    """A group's image: its layer, or the sum of its '<group>_<component>' layers."""
    parts = [image for name, image in layers.items() if name == group or name.startswith(f"{group}_")]
    if not parts:
        raise RelightError(f"the relighter's light groups lack {group!r}")
    return torch.stack(parts).sum(0)


def solve_scales(
    images: torch.Tensor,
    residual: torch.Tensor,
    weights: torch.Tensor,
    current: np.ndarray,
    per_channel: bool,
) -> np.ndarray:
    """Non-negative emission factors x (L, 3) minimising sum_p w_p |residual_p - sum_i x_i (.) U_i,p|^2.

    Args:
        images: (L, H, W, 3) unit images U_i.
        residual: (H, W, 3) target minus the rest of the frame.
        weights: (H, W) non-negative pixel weights (the mask).
        current: (L, 3) the lights' current factors; with `per_channel` False each light's factor
            is a non-negative multiple of its current one (one unknown per light, channels joined).
        per_channel: one unknown per light and channel (colours free) or per light.

    Returns:
        (L, 3) float64 factors.
    """
    # scipy solves on the CPU, in float64, whatever device the images were made on.
    root = torch.sqrt(weights.to("cpu", torch.float64)).reshape(-1, 1)
    columns = images.to("cpu", torch.float64).reshape(images.shape[0], -1, 3) * root  # (L, P, 3)
    rhs = residual.to("cpu", torch.float64).reshape(-1, 3) * root  # (P, 3)
    num_lights = images.shape[0]
    if per_channel:
        factors = np.zeros((num_lights, 3))
        for c in range(3):
            factors[:, c] = _nnls(columns[..., c].T.numpy(), rhs[:, c].numpy())
        return factors
    scaled = columns * torch.as_tensor(current, dtype=torch.float64).unsqueeze(1)
    multiples = _nnls(scaled.reshape(num_lights, -1).T.numpy(), rhs.reshape(-1).numpy())
    return multiples[:, None] * current


def _nnls(matrix: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """argmin_{x >= 0} |A x - b| through the normal equations (L x L: the pixels are many, the
    lights few), columns scaled to unit norm for conditioning."""
    gram = matrix.T @ matrix
    norms = np.sqrt(np.diag(gram))
    live = norms > 0  # a light that reaches no weighted pixel keeps factor 0
    solution = np.zeros(matrix.shape[1])
    if not live.any():
        return solution
    scale = norms[live]
    reduced = gram[np.ix_(live, live)] / np.outer(scale, scale)
    projected = (matrix[:, live].T @ rhs) / scale
    # nnls on the Cholesky factor of the Gram matrix: |R x - R^-T A^T b|^2 = |A x - b|^2 + const.
    factor = np.linalg.cholesky(reduced + 1e-12 * np.eye(reduced.shape[0])).T
    solution[live] = nnls(factor, np.linalg.solve(factor.T, projected))[0] / scale
    return solution


def current_scales(lights: Sequence[Light]) -> np.ndarray:
    """(L, 3) each light's emission factor (`colour_scale`)."""
    return np.stack([colour_scale(light) for light in lights]) if lights else np.zeros((0, 3))
