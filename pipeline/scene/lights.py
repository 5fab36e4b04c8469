"""The shot's lights: every visible UsdLux light prim as a `Light` (via relight_torch.lights.usd).

Unsupported light types (MeshLightAPI, PortalLight, ...) are skipped and light filters and dome
portals ignored, each with a warning; a light with a bad value stops the load with a
`RelightError` naming the prim and attribute.
"""

from __future__ import annotations

from pxr import Usd

from pipeline.errors import RelightError
from relight_torch.lights.light import Light
from relight_torch.lights.usd import read_stage_lights


def read_lights(stage: Usd.Stage, time: Usd.TimeCode, warnings: list[str] | None = None) -> list[Light]:
    """Read the stage's lights at `time`.

    Args:
        stage: the opened shot (schema plugin registered before it was opened).
        time: time code.
        warnings: sink for one-line warnings (e.g. `Scene.warnings`).

    Returns:
        The lights in namespace order, instance proxies included.

    Raises:
        RelightError: a light has a non-finite or out-of-range value, a missing image, or a
            transform its sampler cannot honour.
    """
    try:
        return read_stage_lights(stage, time, warnings)
    except ValueError as error:
        raise RelightError(str(error)) from None
