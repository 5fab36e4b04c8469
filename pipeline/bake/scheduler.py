"""One scheduler for every baker: independent, deterministic chunks, on one machine or many.

A baker's heavy work is cut into chunks that depend only on the shot and the bake's parameters.
Each chunk is computed by a top-level function from a small picklable `ChunkSpec`, in this
process, in a local process pool or on a Dask cluster, and lands as one `.npz` file written
atomically in the bake's chunk folder. A chunk file that exists and is valid (it opens, every
array's CRC holds, and it records the digest of the very spec it was computed for) is never
computed again: a bake killed at any point and run again resumes from its finished chunks.

How to write a baker against it (the transfer and gather bakers are worked examples):

1.  Describe the shot with `ShotSpec.of(scene, camera, time_code)`: paths, not a pickled
    scene (it also remembers `scene`, so chunks run in this process reuse it).
2.  Write a top-level `compute(spec: ChunkSpec) -> dict[str, np.ndarray]`. It re-reads what it
    needs: `load_shot(spec.shot)` (cached per process) and, for derived state (BVH, gathers, view
    samples), a top-level function decorated with `per_process` and keyed by hashable values
    (`spec.shot`, `spec.parameters`), which the driver calls too so in-process chunks share it.
    It must be deterministic: the same spec gives the same arrays, whichever worker runs it. It
    may use `chunk_threads()` threads (torch and Embree release the GIL).
3.  Make the specs: `ChunkSpec(shot, name, parameters, start, stop)` over `chunk_ranges(n, size)`;
    `parameters` is a tuple of (name, value) pairs: everything besides the shot that changes
    the result (not thread counts or batch sizes that only change speed).
4.  `paths = run_chunks(compute, specs, chunk_dir)` returns the chunk files in the order of
    `specs`; read each with `load_chunk(path)` and assemble the payloads. Take `chunk_dir` from
    `chunk_folder(out_dir, stem, work, digest)`, with `digest` the bake's content hash
    (`relight_torch.cache.layer.content_hash` over the inputs, the parameters and
    `pipeline.bake.inputs.code_version()`), so a changed shot, setting or code never meets old
    chunks; remove it once the cache layer is written (see `pipeline.bake.indirect`).

Where the chunks run is the ambient `Scheduler` (`using(scheduler)`, set by `relight bake
--scheduler/--workers`):
    Scheduler()                          in this process, one chunk at a time, its batches on
                                         `chunk_threads()` threads (all CPUs)
    Scheduler(workers=4)                 a local pool of 4 spawned processes, CPUs / 4 threads each
    Scheduler(address="tcp://host:8786") an existing Dask cluster (`distributed.Client(address)`)
    Scheduler(address="dask")            the cluster Dask's configuration names
                                         (`scheduler-address`, e.g. DASK_SCHEDULER_ADDRESS)
    Scheduler(client=client)             a `distributed.Client` the caller holds
Dask workers must see the chunk folder and the shot at the same paths as the driver (a shared
filesystem) and run this code version; each worker loads the shot once per process.

In-process is the local default because the chunk runners already keep every core busy with
threads (torch and Embree release the GIL), while each pool process pays its start (importing
torch and USD, ~3.5 s), reads the shot and rebuilds the BVH: on a 2-core box a Cornell bake took
60 s with 2 processes against 42-50 s in-process (docs/DISTRIBUTED.md). Processes pay off where
chunks are long and GIL-bound. A script that uses a pool must guard its entry point with
`if __name__ == "__main__":` (spawned workers import the main module).
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import functools
import hashlib
import logging
import os
import shutil
import zipfile
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from pipeline.errors import RelightError
from pipeline.progress import progress_bar
from pipeline.scene.load import find_camera, load_scene
from pipeline.scene.types import Camera, Scene
from pipeline.tracing import Tracer, shared_tracer
from relight_torch.io.atomic import atomic_path, remove_temp_files

log = logging.getLogger("relight")

SPEC_KEY = "_chunkSpec"
"""Array in every chunk file holding the digest of the spec it was computed for."""


@dataclass(frozen=True)
class ShotSpec:
    """What a worker needs to read the shot itself.

    Attributes:
        shot: the shot's root layer, absolute path.
        camera: the camera prim path.
        width, height: the camera's resolution in pixels.
        time: the USD time code read, None for the stage's first frame.
        lights_layer: a light-edit layer composed over the shot, None for none.
        read_size: the image size overrides the scene was read with (`Scene.read_size`): its
            subdivision surfaces are refined for the cameras at that size, so a pilot, a
            measurement window or a reduced view of a shot reads the shot's own surfaces.
        film: the camera's (horizontal aperture, vertical aperture, horizontal offset, vertical
            offset) as the bake sees it (a window of the frame is a camera of its own,
            `pipeline.scene.camera.crop`); None: as the stage authors it at width x height.
    """

    shot: str
    camera: str
    width: int
    height: int
    time: float | None = None
    lights_layer: str | None = None
    read_size: tuple[int | None, int | None] = (None, None)
    film: tuple[float, float, float, float] | None = None

    @staticmethod
    def of(scene: Scene, camera: Camera, time_code: float | None = None, lights_layer: str | None = None) -> ShotSpec:
        """The spec of `camera` in `scene` (read by `load_scene(scene.source, time=time_code,
        width=, height=)` at `scene.read_size`, the camera then set to `camera`'s size and film),
        remembered so `load_shot` in this process returns `scene` itself instead of reading it again."""
        shot = ShotSpec(
            str(scene.source),
            camera.path,
            camera.width,
            camera.height,
            None if time_code is None else float(time_code),
            lights_layer,
            scene.read_size,
            (
                camera.horizontal_aperture,
                camera.vertical_aperture,
                camera.horizontal_aperture_offset,
                camera.vertical_aperture_offset,
            ),
        )
        remember_shot(shot, scene)
        return shot


@dataclass(frozen=True)
class ChunkSpec:
    """One chunk: rows [start, stop) of the work `name` of a bake.

    Attributes:
        shot: the shot read.
        name: the work the chunk belongs to (e.g. 'finalGather'), also its file name prefix.
        parameters: (name, value) pairs of everything else that changes the result.
        start, stop: the chunk's range of work items.
        options: (name, value) pairs that change only speed (batch sizes, thread counts): not
            part of the chunk's digest, so changing them keeps finished chunks.
    """

    shot: ShotSpec
    name: str
    parameters: tuple[tuple[str, object], ...]
    start: int
    stop: int
    options: tuple[tuple[str, object], ...] = ()

    @property
    def file_name(self) -> str:
        return f"{self.name}-{self.start:09d}-{self.stop:09d}.npz"

    def param(self, name: str):
        """The value of parameter `name`."""
        return dict(self.parameters)[name]

    def option(self, name: str, default=None):
        """The value of option `name`, `default` when not given."""
        return dict(self.options).get(name, default)


@dataclass(frozen=True)
class Scheduler:
    """Where chunks run (see the module docstring).

    Attributes:
        address: None for local; 'tcp://host:port' (or any Dask scheduler address) for a Dask
            cluster; 'dask' for the address in Dask's configuration.
        workers: local worker processes; None or 1 runs the chunks in this process.
        client: a `distributed.Client` to submit to (overrides `address`).
        progress: show a progress bar (None: when stderr is a terminal).
    """

    address: str | None = None
    workers: int | None = None
    client: object | None = None
    progress: bool | None = None


_SCHEDULER: contextvars.ContextVar[Scheduler | None] = contextvars.ContextVar("relight_scheduler", default=None)
_POOLS: contextvars.ContextVar[_Pools | None] = contextvars.ContextVar("relight_pools", default=None)
_THREADS: contextvars.ContextVar[int | None] = contextvars.ContextVar("relight_chunk_threads", default=None)


@contextlib.contextmanager
def using(scheduler: Scheduler) -> Iterator[Scheduler]:
    """Run every `run_chunks` inside the block on `scheduler`; a local pool it starts serves every
    `run_chunks` of the block (its workers keep their `per_process` state) and stops at its end."""
    token = _SCHEDULER.set(scheduler)
    with contextlib.ExitStack() as stack:
        pool_token = _POOLS.set(_Pools(stack, {}))
        try:
            yield scheduler
        finally:
            _POOLS.reset(pool_token)
            _SCHEDULER.reset(token)


def current() -> Scheduler:
    """The ambient scheduler (`Scheduler()` unless inside `using`)."""
    scheduler = _SCHEDULER.get()
    return Scheduler() if scheduler is None else scheduler


def available_cpus() -> int:
    """CPUs this process may run on."""
    return len(os.sched_getaffinity(0))


def chunk_threads() -> int:
    """Threads a chunk may use: all CPUs in-process, its share of them in a local pool, 1 on a Dask
    worker (a Dask worker already runs one task per thread)."""
    return _THREADS.get() or available_cpus()


def chunk_ranges(total: int, size: int) -> list[tuple[int, int]]:
    """[(start, stop)] cutting range(total) into pieces of `size` (the last may be shorter); one
    empty chunk when `total` is 0 (a camera that sees only sky), so that the joined result of the
    chunks has its usual arrays, empty, rather than none."""
    if size < 1:
        raise ValueError(f"chunk size must be >= 1, got {size}")
    return [(start, min(start + size, total)) for start in range(0, total, size)] or [(0, 0)]


def per_process(function: Callable) -> Callable:
    """Cache `function`'s last two results in this process (keyed by its hashable arguments)."""
    return functools.lru_cache(maxsize=2)(function)


@per_process
def _read_stage(source: str, time: float | None, lights_layer: str | None, read_size: tuple) -> Scene:
    """The shot read once per process per read size: every view of it shares one soup (and BVH)."""
    width, height = read_size
    return load_scene(source, time=time, lights_layer=lights_layer, width=width, height=height)


def _read_shot(shot: ShotSpec) -> Scene:
    """The scene of `shot`: the stage as read at `shot.read_size`, its camera at the spec's size and film."""
    scene = _read_stage(shot.shot, shot.time, shot.lights_layer, shot.read_size)
    camera = dataclasses.replace(find_camera(scene, shot.camera), width=shot.width, height=shot.height)
    if shot.film is not None:
        camera = dataclasses.replace(
            camera,
            horizontal_aperture=shot.film[0],
            vertical_aperture=shot.film[1],
            horizontal_aperture_offset=shot.film[2],
            vertical_aperture_offset=shot.film[3],
        )
    return dataclasses.replace(scene, cameras={**scene.cameras, shot.camera: camera})


_REMEMBERED: dict[ShotSpec, Scene] = {}


def remember_shot(shot: ShotSpec, scene: Scene) -> None:
    """Let `load_shot(shot)` in this process return `scene` (the driver's, already read)."""
    _REMEMBERED.clear()
    _REMEMBERED[shot] = scene


def load_shot(shot: ShotSpec) -> tuple[Scene, Camera]:
    """The shot's scene and camera, read once per process (or the one `remember_shot` gave)."""
    scene = _REMEMBERED[shot] if shot in _REMEMBERED else _read_shot(shot)
    return scene, find_camera(scene, shot.camera)


def shot_tracer(shot: ShotSpec) -> Tracer:
    """The shot's BVH on `chunk_threads()` threads, built once per process and shared with every
    other image size of the same soup (`pipeline.tracing.shared_tracer`)."""
    scene, _ = load_shot(shot)
    return shared_tracer(scene, chunk_threads())


def spec_digest(spec: ChunkSpec) -> str:
    """sha256 of everything in the spec but its options: a chunk file computed for another spec never matches."""
    what = (spec.shot, spec.name, spec.parameters, spec.start, spec.stop)
    return hashlib.sha256(repr(what).encode()).hexdigest()


def load_chunk(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """A chunk file's arrays (without the spec digest); never unpickles.

    Raises:
        RelightError: the file is unreadable or damaged (a zip CRC fails); re-running the bake redoes it.
    """
    try:
        with np.load(path, allow_pickle=False) as saved:
            return {key: saved[key] for key in saved.files if key != SPEC_KEY}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as error:
        raise RelightError(f"{path}: chunk file unreadable ({error}); run the bake again to redo it") from None


def chunk_is_valid(path: Path, digest: str, read_members: bool = True) -> bool:
    """The chunk file exists, was computed for `digest` and (with `read_members`) every array reads
    back (zip CRCs hold). A chunk just written by a worker is checked without `read_members`: its
    arrays are read, CRCs checked, when the bake assembles it (`load_chunk`)."""
    if not path.is_file():
        return False
    try:
        with np.load(path, allow_pickle=False) as saved:
            if SPEC_KEY not in saved.files or str(saved[SPEC_KEY]) != digest:
                return False
            for key in saved.files if read_members else ():
                saved[key]  # reading each member checks its zip CRC (a damaged file raises)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError):
        return False
    return True


def chunk_folder(out_dir: str | os.PathLike, stem: str, work: str, digest: str) -> Path:
    """`out_dir/.<stem>.<work>-<digest[:16]>`, the chunk folder of a bake whose content hash is
    `digest`; the folders of the same stem and work under other hashes (chunks of a changed shot,
    setting or code version, which can never be used again) are deleted."""
    folder = Path(out_dir) / f".{stem}.{work}-{digest[:16]}"
    for stale in Path(out_dir).glob(f".{stem}.{work}-*"):
        if stale.is_dir() and stale != folder:
            log.info("removing the chunks of an earlier bake with other inputs: %s", stale)
            shutil.rmtree(stale, ignore_errors=True)
    return folder


def run_chunk(
    compute: Callable[[ChunkSpec], dict[str, np.ndarray]], spec: ChunkSpec, chunk_dir: str, threads: int | None = None
) -> str:
    """Compute one chunk and write it atomically into `chunk_dir`; the file's path. Runs on workers."""
    token = _THREADS.set(threads)
    try:
        arrays = compute(spec)
    finally:
        _THREADS.reset(token)
    path = Path(chunk_dir) / spec.file_name
    if SPEC_KEY in arrays:
        raise ValueError(f"chunk arrays may not be named {SPEC_KEY}")
    with atomic_path(path) as temp, open(temp, "wb") as handle:
        np.savez(handle, **arrays, **{SPEC_KEY: np.array(spec_digest(spec))})
    return str(path)


def run_chunks(
    compute: Callable[[ChunkSpec], dict[str, np.ndarray]],
    specs: Sequence[ChunkSpec],
    chunk_dir: str | os.PathLike,
    label: str = "chunks",
    unit: str = "items",
    progress: bool | None = None,
) -> list[Path]:
    """Make sure every chunk of `specs` has a valid file in `chunk_dir`; their paths, in order.

    Valid chunk files already there are kept; invalid ones are recomputed. The rest run on the
    ambient scheduler (`current()`).

    Args:
        compute: a top-level function (workers import it by name) spec -> arrays.
        label, unit: progress bar text; progress counts `stop - start` per chunk.
        progress: show the bar; None: as the scheduler says.

    Raises:
        RelightError: a chunk came back invalid; whatever `compute` raised, unchanged.
    """
    chunk_dir = Path(chunk_dir)
    chunk_dir.mkdir(parents=True, exist_ok=True)
    remove_temp_files(chunk_dir)  # of a killed run: no worker of this bake has started yet
    digests = [spec_digest(spec) for spec in specs]
    paths = [chunk_dir / spec.file_name for spec in specs]
    pending = [
        i for i, (path, digest) in enumerate(zip(paths, digests, strict=True)) if not chunk_is_valid(path, digest)
    ]
    scheduler = current()
    total = sum(spec.stop - spec.start for spec in specs)
    done = total - sum(specs[i].stop - specs[i].start for i in pending)
    if len(pending) < len(specs):
        log.info("%s: %d of %d chunks already baked in %s", label, len(specs) - len(pending), len(specs), chunk_dir)
    with progress_bar(label, total, unit, scheduler.progress if progress is None else progress) as update:
        update(done, total)
        for i in _submit(compute, [specs[i] for i in pending], chunk_dir, scheduler, pending):
            if not chunk_is_valid(paths[i], digests[i], read_members=False):
                raise RelightError(
                    f"{paths[i]}: chunk {specs[i].name} [{specs[i].start}, {specs[i].stop}) "
                    f"came back missing or invalid (does the worker see {chunk_dir}?)"
                )
            done += specs[i].stop - specs[i].start
            update(done, total)
    return paths


def _submit(
    compute: Callable, specs: list[ChunkSpec], chunk_dir: Path, scheduler: Scheduler, indices: list[int]
) -> Iterator[int]:
    """Run `specs` where `scheduler` says; yield each finished one's index (from `indices`)."""
    if not specs:
        return
    if scheduler.client is not None or scheduler.address is not None:
        yield from _submit_dask(compute, specs, chunk_dir, scheduler, indices)
        return
    workers = scheduler.workers or 1
    if workers <= 1 or len(specs) == 1:
        for spec, index in zip(specs, indices, strict=True):
            run_chunk(compute, spec, str(chunk_dir))
            yield index
        return
    threads = max(1, available_cpus() // workers)
    with contextlib.ExitStack() as stack:
        pool = _local_pool(workers, _POOLS.get() or _Pools(stack, {}))
        futures = {
            pool.submit(run_chunk, compute, spec, str(chunk_dir), threads): index
            for spec, index in zip(specs, indices, strict=True)
        }
        try:
            for future in as_completed(futures):
                future.result()
                yield futures[future]
        except BaseException:
            for future in futures:
                future.cancel()
            raise


@dataclass
class _Pools:
    """Local pools started inside one `using` block, by size; `stack` stops them at its end."""

    stack: contextlib.ExitStack
    by_size: dict[int, ProcessPoolExecutor]


def _local_pool(workers: int, pools: _Pools) -> ProcessPoolExecutor:
    """The pool of `workers` processes in `pools`, started if there is none yet."""
    if workers not in pools.by_size:
        # spawn, not fork: a forked child inherits torch's and Embree's thread pools in an unknown state.
        pool = ProcessPoolExecutor(workers, mp_context=get_context("spawn"))
        pools.by_size[workers] = pools.stack.enter_context(pool)
    return pools.by_size[workers]


def _submit_dask(
    compute: Callable, specs: list[ChunkSpec], chunk_dir: Path, scheduler: Scheduler, indices: list[int]
) -> Iterator[int]:
    """Run `specs` on a Dask cluster, one task per chunk (one thread each)."""
    try:
        import distributed
    except ImportError:
        raise RelightError(
            "a Dask scheduler needs the 'distributed' extra (pip install relight[distributed])"
        ) from None
    with contextlib.ExitStack() as stack:
        client = scheduler.client
        if client is None:
            address = None if scheduler.address == "dask" else scheduler.address
            if address is None and not _configured_address():
                raise RelightError(
                    "--scheduler dask: Dask's configuration names no scheduler-address "
                    "(set DASK_SCHEDULER_ADDRESS or pass tcp://HOST:PORT)"
                )
            try:
                client = stack.enter_context(distributed.Client(address or _configured_address(), timeout="30s"))
            except (OSError, TimeoutError) as error:
                raise RelightError(
                    f"Dask scheduler {address or _configured_address()}: cannot connect ({str(error).splitlines()[0]})"
                ) from None
        futures = client.map(
            run_chunk, [compute] * len(specs), specs, [str(chunk_dir)] * len(specs), [1] * len(specs), pure=False
        )
        where = dict(zip((f.key for f in futures), indices, strict=True))
        try:
            for future in distributed.as_completed(futures):
                future.result()
                yield where[future.key]
        except BaseException:
            client.cancel(futures)
            raise


def _configured_address() -> str | None:
    """The scheduler address in Dask's configuration, if any."""
    import dask

    return dask.config.get("scheduler-address", None)
