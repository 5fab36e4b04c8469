"""Fixed light samples per shading point, so the relit image is stable while lights are edited.

Each shading point gets S stratified sample positions in [0, 1)^2 (a sqrt(S) x sqrt(S) jittered
grid, or a scrambled Sobol set when S is not a square), shifted by a per-point Cranley-Patterson
rotation drawn once from a fixed seed. The same u are used for every light and every edit.
"""

from __future__ import annotations

import math

import torch

from relight_torch.math.sampling import sobol


def fixed_light_samples(num_points: int, num_samples: int, seed: int = 0,
                        device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(N, S, 2) sample positions in [0, 1), deterministic in (N, S, seed)."""
    if num_samples < 1:
        raise ValueError(f"num_samples must be >= 1, got {num_samples}")
    generator = torch.Generator().manual_seed(seed)
    side = math.isqrt(num_samples)
    if side * side == num_samples:
        grid = (torch.arange(side, dtype=torch.float64) + 0.5) / side
        pattern = torch.stack(torch.meshgrid(grid, grid, indexing="ij"), dim=-1).reshape(-1, 2)
    else:
        pattern = sobol(num_samples, 2, seed=seed, dtype=torch.float64)
    rotation = torch.rand((num_points, 1, 2), generator=generator, dtype=torch.float64)
    u = torch.remainder(pattern.unsqueeze(0) + rotation, 1.0)
    return u.clamp(max=1.0 - 1e-7).to(device=device, dtype=dtype)
