"""Element-wise extremes of a few same-shaped tensors."""

from __future__ import annotations

from collections.abc import Sequence

import torch


def extremes_of_four(values: Sequence[torch.Tensor] | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Element-wise (maximum, minimum) of four same-shaped tensors (or the rows of a (4, ...) tensor):
    three `torch.maximum` / `torch.minimum` each, on the CPU much faster than stacking them and
    reducing over the new axis."""
    return (
        torch.maximum(torch.maximum(values[0], values[1]), torch.maximum(values[2], values[3])),
        torch.minimum(torch.minimum(values[0], values[1]), torch.minimum(values[2], values[3])),
    )
