"""Closed-form intensities and colours: non-negative least squares of per-light images.

Light transport is linear in each light's emission (Schoeneman, Dorsey, Smits, Arvo & Greenberg
1993, "Painting with Light"): with U_i the image of light i at unit emission and F the rest of the
frame (the other lights and the surfaces' own emission), the frame under emission factors x_i is

    image = F + sum_i x_i (.) U_i           (x_i per channel, or a scalar times the current colour)

for every relighting method, indirect light included, so the factors nearest a target in the
mask-weighted least-squares sense are a non-negative least-squares problem per channel. The
images come from the relighter through the `CacheRelighter` protocol alone.

Robust fitting (`huber_weights`): a target made by another renderer, or photographed, disagrees
with the relighter at a few pixels the cache cannot resolve (a highlight of a small light smaller
than the cache's sub-samples, a firefly); in the squared error those few pixels outweigh the rest
of the frame (on the set at 96x72, ten pixels of 6912 carry 86 % of it). Huber's loss (Huber 1964)
counts a pixel's error squared up to HUBER_C robust standard deviations and linearly beyond, and is
minimised by iteratively reweighted least squares (Holland & Welsch 1977): each pass solves the
weighted problem with weights min(1, HUBER_C s / |r_p|) from the last pass's residuals r_p, s their
median absolute value / 0.6745 (the normal's standard deviation for inlying residuals).
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
HUBER_C = 1.345
"""Huber's threshold in robust standard deviations: 95 % of the least-squares efficiency under
Gaussian noise (Holland & Welsch 1977)."""
ROBUST_PASSES = 10
"""Reweighting passes of the robust closed form at most (it stops once no weight moves by 1e-3 of the largest)."""


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


def huber_weights(residual: torch.Tensor, weights: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(H, W) Huber's reweighting (module doc) of the pixel weights `weights` (H, W) for the
    residual (H, W, 3) image - target: a pixel whose residual's length exceeds HUBER_C robust
    standard deviations keeps the share that makes its pull linear in the residual.

    The scale is taken over the pixels of positive weight where the target (H, W, 3) is not black:
    a black background that both fit exactly would otherwise make it 0. Where it is 0 all the same
    (half of those pixels fit exactly) the weights are returned unchanged.
    """
    length = residual.to(torch.float64).norm(dim=-1)
    weights = weights.to(length)
    seen = (weights > 0) & (target.to(length).abs().amax(-1) > 0)
    scale = float(length[seen].median()) / 0.6745 if bool(seen.any()) else 0.0
    if scale == 0.0:
        return weights
    share = (HUBER_C * scale / length.clamp_min(1e-300)).clamp(max=1.0)
    return weights * share


def robust_scales(
    images: torch.Tensor,
    residual: torch.Tensor,
    weights: torch.Tensor,
    current: np.ndarray,
    per_channel: bool,
    target: torch.Tensor,
) -> tuple[np.ndarray, torch.Tensor]:
    """`solve_scales` under Huber's loss (module doc): the factors (L, 3) and the final pixel
    weights (H, W) (`weights` reweighted), by at most ROBUST_PASSES weighted solves; `target`
    (H, W, 3) is the whole target (residual is it less the rest of the frame), for the scale."""
    pixel_weights = weights.to(torch.float64)
    factors = solve_scales(images, residual, pixel_weights, current, per_channel)
    for _ in range(ROBUST_PASSES - 1):
        fitted = torch.einsum("lc,lhwc->hwc", torch.as_tensor(factors).to(images), images)
        updated = huber_weights(fitted.to(torch.float64) - residual.to(torch.float64), weights, target)
        moved = float((updated - pixel_weights).abs().max())
        pixel_weights = updated
        factors = solve_scales(images, residual, pixel_weights, current, per_channel)
        if moved < 1e-3 * float(weights.max()):
            break
    return factors, pixel_weights
