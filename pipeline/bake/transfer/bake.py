"""`relight bake --method transfer`: the direct cache plus gathers and wavelet transfer rows.

Writes into OUT, beside the direct method's payloads (`pipeline.bake.direct`):
    <stem>.viewPixels.npy          (R,) int64 pixel (row * W + col) of each F row: one view
                                   sample per pixel centre (indirect light is smooth; the direct
                                   part keeps the cache's supersampling, as in the chapter)
    <stem>.gather<Field>.npy       the gather cloud (`GatherSamples` fields), texture order
    <stem>.finalGather<Part>.npy   F: Values (nnz, C) float16 | uint8, Scale and Low (R, C)
                                   float32, Indices (nnz,) uint16 (int32 over 65,536 gathers),
                                   Offsets (R + 1,) int64 and, colour-factored (C = 1), Colour
                                   (R, 3) float32 (`relight_torch.transfer.sparse` and `.encoding`)
    <stem>.bounce<Part>.npy        M, the same layout over G rows, when bounces > 1
Rows are baked in chunks saved under `.<stem>.transfer-<hash>/` as they finish; a killed bake
re-run with the same inputs and settings skips the finished chunks. The cache layer is rewritten
last (method 'transfer'), then the chunk directory is removed.
"""

from __future__ import annotations

import dataclasses
import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from pipeline.bake.deep_framebuffer import bake_deep_framebuffer
from pipeline.bake.indirect import start_indirect_bake
from pipeline.bake.direct import write_npy
from pipeline.bake.transfer.gather_cloud import create_gathers
from pipeline.bake.transfer.rows import bounce_rows, final_gather_rows
from pipeline.progress import progress_bar
from pipeline.scene.types import Camera, Scene
from pipeline.tracing import Tracer
from relight_torch.cache.layer import Payload
from relight_torch.io.atomic import atomic_path
from relight_torch.transfer.encoding import ENCODINGS, EncodedRows, EncodedValues, encode_rows
from relight_torch.transfer.haar import haar2d
from relight_torch.transfer.sparse import SparseRows, concatenate, factor_colour, keep_top_k

F_PREFIX, M_PREFIX = "finalGather", "bounce"
_GATHER_FIELDS = ("position", "normal", "albedo", "emission", "area")


@dataclass(frozen=True)
class TransferSettings:
    """What the transfer bake keeps.

    Attributes:
        num_gathers: gather samples, a power of 4 (the chapter: 65,536).
        num_coefficients: wavelet coefficients kept per F row (the chapter: 100).
        num_bounces: indirect bounces B; 1 bakes F only, B > 1 also M (applied B - 1 times).
        num_bounce_coefficients: coefficients kept per M row (the chapter: 40).
        encoding: 'float16' or 'uint8' (8-bit with per-row scale and offset).
        factor_colour: store each row as scalar coefficients times one RGB colour
            (`relight_torch.transfer.sparse.factor_colour`); False keeps RGB coefficients.
        seed: seed of the gather placement.
        rows_per_chunk: rows per resumable chunk file.
        pairs_per_batch: (row, gather) pairs evaluated together (bounds temporaries, ~100 B each).
        num_threads: batches evaluated concurrently (Embree and torch release the GIL); None: the
            CPUs this process may use.
    """

    num_gathers: int = 16384
    num_coefficients: int = 100
    num_bounces: int = 1
    num_bounce_coefficients: int = 40
    encoding: str = "float16"
    factor_colour: bool = True
    seed: int = 0
    rows_per_chunk: int = 4096
    pairs_per_batch: int = 1 << 20
    num_threads: int | None = None

    def check(self) -> None:
        """Raise ValueError naming the first bad setting."""
        side = math.isqrt(max(self.num_gathers, 0))
        if self.num_gathers < 1 or side * side != self.num_gathers or side & (side - 1):
            raise ValueError(f"gathers must be a power of 4 (1024, 4096, 16384, 65536...), got {self.num_gathers}")
        if self.num_coefficients < 1 or self.num_bounce_coefficients < 1:
            raise ValueError("the numbers of kept coefficients must be >= 1")
        if self.num_bounces < 1:
            raise ValueError(f"bounces must be >= 1, got {self.num_bounces}")
        if self.encoding not in ENCODINGS:
            raise ValueError(f"encoding must be one of {ENCODINGS}, got {self.encoding!r}")
        if self.rows_per_chunk < 1 or self.pairs_per_batch < 1 or (self.num_threads or 1) < 1:
            raise ValueError("rows_per_chunk, pairs_per_batch and num_threads must be >= 1")

    def parameters(self) -> dict[str, int | str]:
        """The settings that change the cache, as cache-layer parameters."""
        return {"gathers": self.num_gathers, "coefficients": self.num_coefficients, "bounces": self.num_bounces,
                "bounceCoefficients": self.num_bounce_coefficients, "encoding": self.encoding,
                "rowColour": int(self.factor_colour), "gatherSeed": self.seed}


def compress_rows(dense: torch.Tensor, num_kept: int, factor: bool) -> SparseRows:
    """(R, n, n, 3) dense matrix rows -> their top-k Haar coefficients, optionally colour-factored."""
    coefficients = haar2d(dense)
    if not factor:
        return keep_top_k(coefficients, num_kept)
    scalars, colour = factor_colour(coefficients)
    return dataclasses.replace(keep_top_k(scalars, num_kept), row_colour=colour)


def _bake_chunk(evaluate: Callable[[slice], torch.Tensor], rows: slice, side: int, num_kept: int,
                settings: TransferSettings, update: Callable[[int], None]) -> dict[str, np.ndarray]:
    """Evaluate, transform, cull and encode the rows `rows`; arrays named as the payload parts."""
    batch = max(1, settings.pairs_per_batch // (side * side))
    starts = range(rows.start, rows.stop, batch)

    def work(start: int) -> SparseRows:
        block = evaluate(slice(start, min(start + batch, rows.stop)))
        return compress_rows(block.reshape(-1, side, side, 3), num_kept, settings.factor_colour)

    parts = []
    with ThreadPoolExecutor(settings.num_threads or len(os.sched_getaffinity(0))) as pool:
        for start, part in zip(starts, pool.map(work, starts)):
            parts.append(part)
            update(min(start + batch, rows.stop) - rows.start)
    return encode_rows(concatenate(parts), settings.encoding).arrays()


def bake_rows(evaluate: Callable[[slice], torch.Tensor], num_rows: int, side: int, num_kept: int,
              settings: TransferSettings, chunk_dir: Path, name: str, progress: bool | None = None) -> EncodedRows:
    """All rows of one matrix, chunk by chunk, reusing the chunks `chunk_dir` already holds.

    Args:
        evaluate: rows (a slice) -> (R, G, 3) dense matrix rows, gathers in texture order; called
            from `settings.num_threads` threads at once.
        num_rows: rows of the matrix; side: n (G = n^2); num_kept: coefficients per row.
        chunk_dir: where finished chunks are saved (`<name>-<first row>.npz`, written atomically).
    """
    chunks = []
    with progress_bar(f"{name} rows", num_rows, "rows", progress) as update:
        for first in range(0, num_rows, settings.rows_per_chunk):
            rows = slice(first, min(first + settings.rows_per_chunk, num_rows))
            path = chunk_dir / f"{name}-{first:09d}.npz"
            if not path.is_file():
                arrays = _bake_chunk(evaluate, rows, side, num_kept, settings,
                                     lambda done, first=first: update(first + done, num_rows))
                with atomic_path(path) as temp:
                    with open(temp, "wb") as handle:
                        np.savez(handle, **arrays)
            with np.load(path, allow_pickle=False) as saved:
                chunks.append(EncodedRows.from_arrays({key: saved[key] for key in saved.files}, side * side))
            update(rows.stop, num_rows)
    starts = np.cumsum([0] + [int(c.offsets[-1]) for c in chunks[:-1]])
    offsets = torch.cat([chunks[0].offsets[:1]] + [c.offsets[1:] + int(s) for c, s in zip(chunks, starts)])

    def join(get: Callable[[EncodedRows], torch.Tensor]) -> torch.Tensor:
        return torch.cat([get(c) for c in chunks])

    colour = None if chunks[0].row_colour is None else join(lambda c: c.row_colour)
    values = EncodedValues(join(lambda c: c.values.stored), join(lambda c: c.values.scale),
                           join(lambda c: c.values.low))
    return EncodedRows(values, join(lambda c: c.indices), offsets, side * side, colour)


def matrix_payloads(out_dir: Path, stem: str, prefix: str, rows: EncodedRows) -> list[Payload]:
    """Write the parts of one matrix as `<stem>.<prefix><Part>.npy`; their payload records."""
    return [write_npy(Path(out_dir) / f"{stem}.{prefix}{part}.npy", np.ascontiguousarray(array), name=prefix + part)
            for part, array in rows.arrays().items()]


def bake_transfer(scene: Scene, camera: Camera, out_dir: str | Path, stem: str, supersampling: int = 2,
                  texture_samples: int = 2, time_code: float | None = None,
                  settings: TransferSettings = TransferSettings(), progress: bool | None = None) -> Path:
    """Bake the transfer cache of `camera`; returns the cache layer's path.

    Args:
        supersampling: of the direct part (F has one row per covered pixel centre).
        texture_samples: material samples per sub-sample side (texture filtering).
        time_code: the time the scene was read at.
        settings: gathers, kept coefficients, bounces, encoding.
        progress: show progress bars (None: when stderr is a terminal).

    Raises:
        ValueError: bad settings (see `TransferSettings.check`, `create_gathers`).
    """
    settings.check()
    bake = start_indirect_bake(scene, camera, out_dir, stem, "transfer", settings.parameters(), supersampling,
                               texture_samples, time_code)
    chunk_dir = bake.chunk_dir

    tracer = Tracer(scene.geometry)
    view = bake_deep_framebuffer(scene, camera, 1, texture_samples, tracer=tracer).gbuffer
    gathers = create_gathers(scene, settings.num_gathers, settings.seed)
    payloads = [bake.payload(stem, "viewPixels", view.pixel_index.numpy())]
    payloads += [bake.payload(stem, "gather" + name.capitalize(), getattr(gathers, name).numpy())
                 for name in _GATHER_FIELDS]
    final_gather = bake_rows(lambda rows: final_gather_rows(view, rows, gathers, tracer), view.num_samples,
                             gathers.side, settings.num_coefficients, settings, chunk_dir, F_PREFIX, progress)
    payloads += matrix_payloads(bake.out_dir, stem, F_PREFIX, final_gather)
    if settings.num_bounces > 1:
        bounce = bake_rows(lambda rows: bounce_rows(rows, gathers, tracer), gathers.num_gathers, gathers.side,
                           settings.num_bounce_coefficients, settings, chunk_dir, M_PREFIX, progress)
        payloads += matrix_payloads(bake.out_dir, stem, M_PREFIX, bounce)
    return bake.finish(payloads)
