"""Bench adapter of the transfer method: gathers x kept coefficients, one bake per gather count.

Each gather count is baked once keeping the largest coefficient count; every smaller count is
studied by culling those rows (`relight_torch.transfer.sparse.cull`, the bake's own order) and,
when the bake refitted its rows to light probes, refitting the culled rows to the products the
baked rows have with the probes a bake at that count keeps (the first `probe_budget(count)`,
`pipeline.bake.transfer.probes`; `relight_torch.transfer.responses`): the baked rows keep the
untruncated rows' products, so the culled ones do as a bake at that count would. bake_s is
that one bake's time for all of them and cache_bytes counts the culled matrix as the layer would
store it (its parts written under `<cache>/culled`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch

from pipeline.bake.adapter import Variant
from pipeline.bake.transfer.bake import F_PREFIX, PROBES_PAYLOAD, TransferSettings, bake_transfer, matrix_payloads
from pipeline.bake.transfer.probes import probe_budget
from pipeline.scene.types import Camera, Scene
from relight_torch.cache.layer import read_cache_layer
from relight_torch.cache.load import load_npy
from relight_torch.transfer.encoding import decode_rows, encode_rows
from relight_torch.transfer.open import open_transfer_relighter
from relight_torch.transfer.relighter import TransferRelighter
from relight_torch.transfer.responses import refit_rows, sparse_responses
from relight_torch.transfer.sparse import cull


def kept_counts(point: dict[str, object]) -> list[int]:
    """The point's coefficient counts, increasing (an int or a tuple of them; default the bake's)."""
    value = point.get("coefficients", TransferSettings().num_coefficients)
    return sorted(value) if isinstance(value, tuple) else [int(value)]


def settings(point: dict[str, object]) -> TransferSettings:
    """The bake settings of a point (keys gathers, coefficients, bounces, bounceCoefficients), keeping the
    most coefficients."""
    defaults = TransferSettings()
    return TransferSettings(
        num_gathers=int(point.get("gathers", defaults.num_gathers)),
        num_coefficients=kept_counts(point)[-1],
        num_bounces=int(point.get("bounces", defaults.num_bounces)),
        num_bounce_coefficients=int(point.get("bounceCoefficients", defaults.num_bounce_coefficients)),
    )


class TransferAdapter:
    """Precomputed wavelet transfer (final gather F, bounce matrix M for bounces > 1)."""

    name = "transfer"
    chart_axes = ("coefficients", "gathers")

    def grid(self, quick: bool) -> list[dict[str, object]]:
        if quick:
            return [{"gathers": 1024, "coefficients": (10, 50), "bounces": 1}]
        return [
            {"gathers": gathers, "coefficients": (10, 25, 50, 100, 200), "bounces": 1}
            for gathers in (1024, 4096, 16384)
        ]

    def bounces(self, point: dict[str, object]) -> int:
        return settings(point).num_bounces

    def bake(
        self,
        scene: Scene,
        camera: Camera,
        directory: Path,
        stem: str,
        point: dict[str, object],
        supersampling: int,
        texture_samples: int,
        time_code: float | None = None,
    ) -> Path:
        supersampling = int(point.get("supersampling", supersampling))
        return bake_transfer(
            scene,
            camera,
            directory,
            stem,
            supersampling,
            texture_samples,
            time_code=time_code,
            settings=settings(point),
            progress=False,
        )

    def variants(self, layer: Path, point: dict[str, object], device: str) -> list[Variant]:
        baked = open_transfer_relighter(layer, device=device)
        return culled_variants(layer, baked, settings(point), kept_counts(point))


def culled_variants(
    layer: Path, baked: TransferRelighter, baked_settings: TransferSettings, counts: list[int]
) -> list[Variant]:
    """One variant per kept coefficient count of the cache `layer` opened as `baked`: its F rows
    culled to that count and encoded as the bake would (parts written under `<cache>/culled`,
    counted in the variant's cache bytes)."""
    description = read_cache_layer(layer)
    # The settings as baked: the indirect scale sized from the image is the layer's.
    parameters = dataclasses.replace(
        baked_settings, indirect_scale=int(description.parameters["indirectScale"])
    ).parameters()
    base_bytes = sum(p.num_bytes for p in description.payloads if not p.name.startswith(F_PREFIX))
    stored = baked.final_gather.to("cpu", baked.final_gather.values.dtype)
    device = baked.final_gather.values.device
    culled_dir = layer.parent / "culled"
    culled_dir.mkdir(exist_ok=True)
    probes = None
    if int(description.parameters.get("lightProbes", 0)):
        probes = torch.from_numpy(np.array(load_npy(layer, description, PROBES_PAYLOAD)))
        target = sparse_responses(stored, probes)
    out = []
    for num_kept in counts:
        rows = cull(stored, num_kept)
        if probes is not None:
            kept_probes = probe_budget(num_kept)
            rows = refit_rows(rows, probes[:kept_probes], target[:, :kept_probes])
        encoded = encode_rows(rows, baked_settings.encoding)
        payloads = matrix_payloads(culled_dir, f"{layer.name.split('.')[0]}-{num_kept}", F_PREFIX, encoded)
        final_gather = decode_rows(encoded).to(device, stored.values.dtype)
        relighter = TransferRelighter(
            baked.direct,
            baked.gathers,
            baked.view_pixels,
            final_gather,
            baked.bounce,
            baked.num_bounces,
            upsampler=baked.upsampler,
        )
        out.append(
            Variant(
                {**parameters, "coefficients": num_kept}, relighter, base_bytes + sum(p.num_bytes for p in payloads)
            )
        )
    return out


ADAPTER = TransferAdapter()
