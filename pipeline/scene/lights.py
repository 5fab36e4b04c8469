"""The shot's lights: every visible UsdLux light prim as a `Light` (via relight_torch.lights.usd).

Unsupported light types (MeshLightAPI, PortalLight, ...) are skipped with a warning; light
filters and dome portals are ignored with a warning; a light with a bad value stops the load with
a `RelightError` naming the prim and attribute.
"""

from __future__ import annotations

from pxr import Usd, UsdLux

from pipeline.errors import RelightError, warn
from relight_torch.lights.light import Light
from relight_torch.lights.usd import iter_light_prims, light_kind, read_light


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
    lights = []
    for prim in iter_light_prims(stage, time):
        if light_kind(prim) is None:
            warn(f"{prim.GetPath()}: light type '{prim.GetTypeName()}' is not supported; skipped",
                 warnings)
            continue
        if UsdLux.LightAPI(prim).GetFiltersRel().GetTargets():
            warn(f"{prim.GetPath()}: light:filters are not supported; ignored", warnings)
        if prim.HasRelationship("portals") and prim.GetRelationship("portals").GetTargets():
            warn(f"{prim.GetPath()}: dome light portals are not supported; ignored", warnings)
        try:
            lights.append(read_light(prim, time))
        except ValueError as error:
            raise RelightError(str(error)) from None
    return lights
