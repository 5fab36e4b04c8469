"""What a direct cache is opened with besides its G-buffer (`relighter.open_relighter`): the shot's
lights, and the occluders as shadow-ray visibility, with their opacity table."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from relight_torch.cache.layer import CacheDescription
from relight_torch.cache.load import load_npy
from relight_torch.errors import RelightError
from relight_torch.lights.light import Light
from relight_torch.lights.usd import read_stage_lights
from relight_torch.stage import check_composition, defining_layer, open_stage, outside_reads, time_code
from relight_torch.visibility.embree import EmbreeCaster, ShadowLinkCasters
from relight_torch.visibility.opacity import OPACITY_PAYLOADS, OpacityTable
from relight_torch.visibility.rays import RayVisibility


def embree_visibility(
    occluders: np.ndarray,
    occluder_objects: np.ndarray | None,
    object_paths: list[str] | None,
    opacity: OpacityTable | None = None,
) -> tuple[EmbreeCaster, RayVisibility]:
    """Embree over a cache's (T, 3, 3) occluders and the shadow-ray visibility using it, with a
    caster per shadow-link set when the (T,) occluder objects and their paths are given; shadow
    rays pass through the holes of the occluders' `opacity` table (`load_opacity`)."""
    caster = EmbreeCaster(occluders, opacity=opacity)
    links = None
    if occluder_objects is not None:
        assert object_paths is not None, "occluder objects come with the paths they index"
        links = ShadowLinkCasters(occluders, occluder_objects, object_paths, caster.epsilon, opacity=opacity)
    return caster, RayVisibility(caster, links)


def load_opacity(layer_path: Path, description: CacheDescription) -> OpacityTable | None:
    """The occluders' opacity table of a cache (`OpacityTable.to_arrays` payloads), None when the
    bake found every occluder opaque (and wrote none)."""
    names = {payload.name for payload in description.payloads}
    if OPACITY_PAYLOADS[0] not in names:
        return None
    try:
        return OpacityTable.from_arrays({name: load_npy(layer_path, description, name) for name in OPACITY_PAYLOADS})
    except (KeyError, ValueError) as error:
        raise RelightError(f"{layer_path}: occluder opacity payloads: {error}") from error


def shot_lights(description: CacheDescription, lights_layer: str | os.PathLike[str] | None = None) -> list[Light]:
    """The lights of the cache's shot, at the baked time, with `lights_layer` composed over them.

    Raises:
        RelightError: a file cannot be opened, or a light has a bad value (naming prim and attribute).
    """
    stage = open_stage(description.source, lights_layer)
    shot = os.fspath(lights_layer or description.source)
    check_composition(stage, shot)
    for line in outside_reads(description.source, lights_layer) if lights_layer is not None else []:
        logging.getLogger("relight").warning(line)
    time = description.parameters.get("time")
    try:
        return read_stage_lights(stage, time_code(stage, None if time is None else float(time)))
    except ValueError as error:
        raise RelightError(f"{defining_layer(stage, str(error), shot)}: {error}") from None
