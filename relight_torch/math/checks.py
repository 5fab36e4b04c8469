"""The one shape check used at the public boundary of the torch kernels."""

from __future__ import annotations

import torch


def check_last_dim(tensor: torch.Tensor, size: int, name: str) -> None:
    """Raise ValueError unless `tensor` is a torch tensor of shape (..., size).

    Args:
        tensor: the argument to check.
        size: the required length of the last axis (3 for directions and colours, 2 for
            random numbers).
        name: the argument's name, quoted in the error.
    """
    if not isinstance(tensor, torch.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor of shape (..., {size}); got {type(tensor).__name__}")
    if tensor.dim() == 0 or tensor.shape[-1] != size:
        raise ValueError(f"{name} must have shape (..., {size}); got {tuple(tensor.shape)}")
