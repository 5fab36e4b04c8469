"""`relight bake --method transfer`: the direct cache plus gathers and wavelet transfer rows.

Writes into OUT, beside the direct method's payloads (`pipeline.bake.direct.bake`):
    <stem>.viewPixels.npy          (R,) int64 pixel (row * W + col) of each F row, a covered
                                   pixel: the mean of the rows of its sub-samples, on the direct
                                   part's s x s grid (`view_supersampling`); with --indirect-scale
                                   s > 1, one view sample per pixel centre of the image reduced s
                                   times per side
    <stem>.view<Field>.npy         with --indirect-scale s > 1: Position, Normal (geometric) (R, 3)
                                   float32 and ObjectId (R,) int32 of the coarse view samples
    <stem>.gather<Field>.npy       the gather cloud (`GatherSamples` fields), texture order;
                                   gatherObjectId (G,) int64 indexes the objectPaths payload
    <stem>.finalGather<Part>.npy   F: Values (nnz, C) float16 | uint8, Scale and Low (R, C)
                                   float32, Indices (nnz,) uint16 (int32 over 65,536 gathers),
                                   Offsets (R + 1,) int64 and, colour-factored (C = 1), Colour
                                   (R, 3) float32 (`relight_torch.transfer.sparse` and `.encoding`)
    <stem>.bounce<Part>.npy        M, the same layout over G rows, when bounces > 1
    <stem>.transferProbes.npy      (Q, G) float32 Haar coefficients of the probe lights whose
                                   products each F row keeps exactly (`pipeline.bake.transfer.probes`,
                                   `relight_torch.transfer.responses`); with light probes on
M is baked first: the probes are the shot's lights carried through its bounces.
Rows are baked in chunks saved under `.<stem>.transfer-<hash>/` as they finish; a killed bake
re-run with the same inputs and settings skips the finished chunks. The cache layer is rewritten
last (method 'transfer'), then the chunk directory is removed.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pipeline.bake.direct.bake import write_npy
from pipeline.bake.gather_cloud import create_gathers
from pipeline.bake.indirect import PixelViews, pixel_views, start_indirect_bake
from pipeline.bake.scheduler import (
    ChunkSpec,
    ShotSpec,
    chunk_ranges,
    chunk_threads,
    load_chunk,
    load_shot,
    per_process,
    run_chunks,
    shot_tracer,
)
from pipeline.bake.transfer.probes import probe_lights
from pipeline.bake.transfer.rows import bounce_rows, disc_support, final_gather_rows
from pipeline.scene.types import Camera, Scene
from pipeline.tracing import Tracer
from relight_torch.cache.layer import Payload
from relight_torch.indirect_samples import GatherSamples, gather_payload_name
from relight_torch.transfer.encoding import ENCODINGS, EncodedRows, EncodedValues, decode_rows, encode_rows
from relight_torch.transfer.haar import haar2d
from relight_torch.transfer.responses import dense_responses, refit_rows
from relight_torch.transfer.sparse import SparseRows, concatenate, factor_colour, keep_top_k

F_PREFIX, M_PREFIX = "finalGather", "bounce"
PROBES_PAYLOAD = "transferProbes"


@dataclass(frozen=True)
class TransferSettings:
    """What the transfer bake keeps.

    Attributes:
        num_gathers: gather samples, a power of 4 (the chapter: 65,536). 4,096 by default: with
            100 coefficients per row more gathers lower the PSNR (Cornell box 192x192, shot /
            move / white light / focus: 1,024 gathers 37.8 / 36.6 / 38.8 / 35.2 dB, 4,096 37.2 /
            35.9 / 38.1 / 34.6, 16,384 37.0 / 35.7 / 38.0 / 34.5; docs/TRANSFER.md) and cost 4x
            the bake and the gather light per step; 4,096 beats 1,024 on the glossy scene.
        num_coefficients: wavelet coefficients kept per F row (the chapter: 100).
        num_bounces: indirect bounces B; 1 bakes F only, B > 1 also M (applied B - 1 times).
        num_bounce_coefficients: coefficients kept per M row (the chapter: 40).
        encoding: 'float16' or 'uint8' (8-bit with per-row scale and offset).
        light_probes: refit each F row's kept coefficients so that it transfers the shot's own
            lights (through the bounces) exactly (`relight_torch.transfer.responses`): top-k
            culling alone lost 3-7 % of the Cornell box's indirect light at 50 of 1,024
            coefficients, 1-4 % at 100 (docs/TRANSFER.md).
        factor_colour: store each row as scalar coefficients times one RGB colour
            (`relight_torch.transfer.sparse.factor_colour`); False keeps RGB coefficients.
        seed: seed of the gather placement.
        rows_per_chunk: rows per resumable chunk file.
        pairs_per_batch: (row, gather) pairs evaluated together (bounds temporaries, ~100 B each).
        num_threads: batches evaluated concurrently (Embree and torch release the GIL); None: the
            CPUs this process may use.
        indirect_scale: s >= 1: F has one row per pixel centre of the image reduced s times per
            side (the shot's width and height must be multiples of s), and the relighter brings
            its indirect image back to full size with an edge-aware filter guided by the direct
            deep framebuffer (`relight_torch.transfer.upsample`): s^2 fewer F rows to bake, store
            and multiply per light edit. None: sized from the image (`auto_indirect_scale`).
    """

    num_gathers: int = 4096
    num_coefficients: int = 100
    num_bounces: int = 1
    num_bounce_coefficients: int = 40
    encoding: str = "float16"
    light_probes: bool = True
    factor_colour: bool = True
    seed: int = 0
    rows_per_chunk: int = 4096
    pairs_per_batch: int = 1 << 20
    num_threads: int | None = None
    indirect_scale: int | None = None

    def for_view(self, camera: Camera) -> TransferSettings:
        """These settings with the indirect scale resolved for `camera`'s image."""
        if self.indirect_scale is not None:
            return self
        return dataclasses.replace(self, indirect_scale=auto_indirect_scale(camera.width, camera.height))

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
        if self.indirect_scale is not None and self.indirect_scale < 1:
            raise ValueError(f"indirect scale must be >= 1, got {self.indirect_scale}")

    def parameters(self) -> dict[str, int | str]:
        """The settings that change the cache, as cache-layer parameters (the indirect scale
        resolved: see `for_view`)."""
        if self.indirect_scale is None:
            raise ValueError("the indirect scale is sized from the image: resolve it with for_view(camera)")
        return {
            "gathers": self.num_gathers,
            "coefficients": self.num_coefficients,
            "bounces": self.num_bounces,
            "bounceCoefficients": self.num_bounce_coefficients,
            "encoding": self.encoding,
            "lightProbes": int(self.light_probes),
            "rowColour": int(self.factor_colour),
            "gatherSeed": self.seed,
            "indirectScale": self.indirect_scale,
        }


def auto_indirect_scale(width: int, height: int) -> int:
    """The default indirect scale of a width x height image: 2 from 240 pixels on the shorter
    side (when both sides are even), else 1.

    Indirect light is smooth and the edge-aware upsampling keeps its edges: on the Cornell box,
    scale 2 matched scale 1 within 0.02 dB at 320 x 240 and at 640 x 480 (full and indirect PSNR
    against 64- and 128-path references, docs/TRANSFER.md) for a quarter of the bake's CPU time,
    a third of the cache and a quarter of F's entries per light edit. At 32 x 32 it lost 1.2 dB of
    indirect PSNR: small images keep one row per pixel.
    """
    return 2 if min(width, height) >= 240 and width % 2 == 0 and height % 2 == 0 else 1


def compress_rows(dense: torch.Tensor, num_kept: int, factor: bool, probes: torch.Tensor | None = None) -> SparseRows:
    """(R, n, n, 3) dense matrix rows -> their top-k Haar coefficients, optionally colour-factored,
    refitted to keep their products with the (Q, n^2) wavelet `probes` when given (`refit_rows`)."""
    coefficients = haar2d(dense)
    colour = None
    if factor:
        coefficients, colour = factor_colour(coefficients)
    kept = keep_top_k(coefficients, num_kept)
    if probes is not None and probes.shape[0]:
        kept = refit_rows(kept, probes, dense_responses(coefficients, probes))
    return dataclasses.replace(kept, row_colour=colour)


@per_process
def transfer_inputs(
    shot: ShotSpec, texture_samples: int, num_gathers: int, seed: int, view_supersampling: int = 1
) -> tuple[Tracer, PixelViews, GatherSamples, torch.Tensor]:
    """The shot's BVH, view samples (`view_supersampling`^2 per pixel, `pixel_views`), gathers and
    their discs' support on the surfaces (`rows.disc_support`), built once per process."""
    scene, _ = load_shot(shot)
    tracer = shot_tracer(shot)
    gathers = create_gathers(scene, num_gathers, seed)
    views = pixel_views(shot, texture_samples, view_supersampling)
    return tracer, views, gathers, disc_support(gathers, tracer)


def view_supersampling(supersampling: int, indirect_scale: int) -> int:
    """Sub-samples per pixel side that each F row box-filters: the direct part's `supersampling` at
    indirect scale 1 (the row is then the pixel's own mean, as the direct image is), else 1 (a
    coarse row is a point value the edge-aware upsampler interpolates)."""
    return supersampling if indirect_scale == 1 else 1


def pixel_final_gather_rows(
    views: PixelViews, rows: slice, gathers: GatherSamples, caster: Tracer, support: torch.Tensor | None
) -> torch.Tensor:
    """(R, G, 3) F rows [start, stop) of `views`: each the mean of its pixel's s x s sub-samples'
    rows (`final_gather_rows`), an uncovered sub-sample counting as zero."""
    samples, owner = views.row_samples(rows)
    sub_rows = final_gather_rows(views.samples, samples, gathers, caster, support)
    summed = sub_rows.new_zeros((rows.stop - rows.start, *sub_rows.shape[1:])).index_add_(0, owner, sub_rows)
    return summed / views.supersampling**2


def _bake_chunk(spec: ChunkSpec) -> dict[str, np.ndarray]:
    """Evaluate, transform, cull and encode rows [start, stop) of matrix `spec.name` (F_PREFIX or
    M_PREFIX); arrays named as the payload parts. Batches of rows run on `chunk_threads()` threads."""
    tracer, views, gathers, support = transfer_inputs(
        spec.shot,
        spec.param("textureSamples"),
        spec.param("gathers"),
        spec.param("gatherSeed"),
        spec.param("viewSupersampling"),
    )
    side, num_kept = gathers.side, spec.param("coefficients")
    per_row = side * side * (views.supersampling**2 if spec.name == F_PREFIX else 1)
    batch = max(1, spec.option("pairsPerBatch", TransferSettings.pairs_per_batch) // per_row)
    probes_path = spec.option("probes")
    probes = None if probes_path is None else torch.from_numpy(np.load(probes_path, allow_pickle=False))

    def work(start: int) -> SparseRows:
        rows = slice(start, min(start + batch, spec.stop))
        block = (
            pixel_final_gather_rows(views, rows, gathers, tracer, support)
            if spec.name == F_PREFIX
            else bounce_rows(rows, gathers, tracer, support)
        )
        return compress_rows(block.reshape(-1, side, side, 3), num_kept, bool(spec.param("rowColour")), probes)

    with ThreadPoolExecutor(spec.option("threads") or chunk_threads()) as pool:
        # An empty chunk (a camera that sees only sky) is one empty batch: rows of the right layout.
        parts = list(pool.map(work, range(spec.start, spec.stop, batch) or [spec.start]))
    return encode_rows(concatenate(parts), spec.param("encoding")).arrays()


def bake_rows(
    shot: ShotSpec,
    name: str,
    num_rows: int,
    num_kept: int,
    texture_samples: int,
    settings: TransferSettings,
    chunk_dir: Path,
    progress: bool | None = None,
    probes: Payload | None = None,
    probes_path: Path | None = None,
    view_supersampling: int = 1,
) -> EncodedRows:
    """All rows of matrix `name` (F_PREFIX or M_PREFIX) in chunks on the ambient scheduler
    (`pipeline.bake.scheduler`), reusing the valid chunks `chunk_dir` already holds.

    Args:
        shot: the shot the rows are of (workers read it and build `transfer_inputs`).
        num_rows: rows of the matrix; num_kept: coefficients per row.
        texture_samples: of the view samples.
        chunk_dir: where finished chunks are saved.
        probes, probes_path: the probe lights' payload record and file (workers read it), whose
            products the rows keep (`compress_rows`); None for plain top-k rows.
        view_supersampling: sub-samples per pixel side of each F row (`view_supersampling`).
    """
    parameters = (
        ("textureSamples", texture_samples),
        ("gathers", settings.num_gathers),
        ("gatherSeed", settings.seed),
        ("coefficients", num_kept),
        ("encoding", settings.encoding),
        ("rowColour", settings.factor_colour),
        ("probes", None if probes is None else probes.sha256),
        ("viewSupersampling", view_supersampling),
    )
    options = (
        ("pairsPerBatch", settings.pairs_per_batch),
        ("threads", settings.num_threads),
        ("probes", None if probes_path is None else str(probes_path)),
    )
    specs = [
        ChunkSpec(shot, name, parameters, start, stop, options)
        for start, stop in chunk_ranges(num_rows, settings.rows_per_chunk)
    ]
    num_gathers = settings.num_gathers
    chunks = [
        EncodedRows.from_arrays(load_chunk(path), num_gathers)
        for path in run_chunks(_bake_chunk, specs, chunk_dir, f"{name} rows", "rows", progress)
    ]
    starts = np.cumsum([0] + [int(c.offsets[-1]) for c in chunks[:-1]])
    offsets = torch.cat([chunks[0].offsets[:1]] + [c.offsets[1:] + int(s) for c, s in zip(chunks, starts, strict=True)])

    def join(get: Callable[[EncodedRows], torch.Tensor]) -> torch.Tensor:
        return torch.cat([get(c) for c in chunks])

    colour = None if chunks[0].row_colour is None else join(lambda c: c.row_colour)
    values = EncodedValues(
        join(lambda c: c.values.stored), join(lambda c: c.values.scale), join(lambda c: c.values.low)
    )
    return EncodedRows(values, join(lambda c: c.indices), offsets, num_gathers, colour)


def matrix_payloads(out_dir: Path, stem: str, prefix: str, rows: EncodedRows) -> list[Payload]:
    """Write the parts of one matrix as `<stem>.<prefix><Part>.npy`; their payload records."""
    return [
        write_npy(Path(out_dir) / f"{stem}.{prefix}{part}.npy", np.ascontiguousarray(array), name=prefix + part)
        for part, array in rows.arrays().items()
    ]


def reduced_view(scene: Scene, camera: Camera, scale: int) -> tuple[Scene, Camera]:
    """The scene with its cameras' resolutions divided by `scale`, and `camera` so reduced: the
    view of the F rows (the same frustum, one view sample per s x s block of pixels).

    Raises:
        ValueError: the camera's width or height is not a multiple of `scale`.
    """
    if scale == 1:
        return scene, camera
    if camera.width % scale or camera.height % scale:
        raise ValueError(f"the indirect scale {scale} must divide the image size {camera.width}x{camera.height}")
    cameras = {
        path: dataclasses.replace(c, width=c.width // scale, height=c.height // scale)
        for path, c in scene.cameras.items()
    }
    return dataclasses.replace(scene, cameras=cameras), cameras[camera.path]


def bake_transfer(
    scene: Scene,
    camera: Camera,
    out_dir: str | Path,
    stem: str,
    supersampling: int = 2,
    texture_samples: int = 2,
    time_code: float | None = None,
    settings: TransferSettings = TransferSettings(),
    progress: bool | None = None,
) -> Path:
    """Bake the transfer cache of `camera`; returns the cache layer's path.

    Args:
        supersampling: of the direct part (F has one row per covered pixel centre).
        texture_samples: material samples per sub-sample side (texture filtering).
        time_code: the time the scene was read at.
        settings: gathers, kept coefficients, bounces, encoding.
        progress: show progress bars (None: when stderr is a terminal).

    Raises:
        ValueError: bad settings (see `TransferSettings.check`, `create_gathers`, `reduced_view`).
    """
    settings = settings.for_view(camera)
    settings.check()
    reduced_view(scene, camera, settings.indirect_scale)
    bake = start_indirect_bake(
        scene, camera, out_dir, stem, "transfer", settings.parameters(), supersampling, texture_samples, time_code
    )
    chunk_dir = bake.chunk_dir

    shot = ShotSpec.of(*reduced_view(scene, camera, settings.indirect_scale), time_code)
    sub = view_supersampling(supersampling, settings.indirect_scale)
    tracer, views, gathers, _ = transfer_inputs(shot, texture_samples, settings.num_gathers, settings.seed, sub)
    payloads = [bake.payload(stem, "viewPixels", views.pixels.numpy())]
    if settings.indirect_scale > 1:  # what the edge-aware upsampling weighs the coarse samples by
        view = views.samples  # one sample per coarse pixel, at its centre
        payloads += [
            bake.payload(stem, "viewPosition", view.position.numpy()),
            bake.payload(stem, "viewNormal", view.geometric_normal.numpy()),
            bake.payload(stem, "viewObjectId", view.object_id.numpy()),
        ]
    payloads += [
        bake.payload(stem, gather_payload_name(name), getattr(gathers, name).numpy())
        for name in (f.name for f in dataclasses.fields(GatherSamples))
    ]
    bounce = None
    if settings.num_bounces > 1:
        encoded = bake_rows(
            shot,
            M_PREFIX,
            gathers.num_gathers,
            settings.num_bounce_coefficients,
            texture_samples,
            settings,
            chunk_dir,
            progress,
            view_supersampling=sub,
        )
        payloads += matrix_payloads(bake.out_dir, stem, M_PREFIX, encoded)
        bounce = decode_rows(encoded)
    probes = probes_path = None
    if settings.light_probes:
        probes = bake.payload(
            stem,
            PROBES_PAYLOAD,
            probe_lights(
                scene, gathers, tracer, bounce, settings.num_bounces, settings.num_coefficients, settings.seed
            ).numpy(),
        )
        probes_path = bake.out_dir / probes.file
        payloads.append(probes)
    final_gather = bake_rows(
        shot,
        F_PREFIX,
        views.num_rows,
        settings.num_coefficients,
        texture_samples,
        settings,
        chunk_dir,
        progress,
        probes,
        probes_path,
        sub,
    )
    payloads += matrix_payloads(bake.out_dir, stem, F_PREFIX, final_gather)
    return bake.finish(payloads)
