"""Lighting by example: light settings solved from a target image through a relighter (docs/SOLVE.md).

`solve_lights(relighter, target, ...)` (`relight_torch.solve.solver`); the free kinds and how a
solved emission is written back as UsdLux inputs: `relight_torch.solve.rig`.
"""

from relight_torch.solve.descent import DescentSettings
from relight_torch.solve.rig import FREE_KINDS, parse_free
from relight_torch.solve.solver import SolveResult, solve_lights

__all__ = ["FREE_KINDS", "DescentSettings", "SolveResult", "parse_free", "solve_lights"]
