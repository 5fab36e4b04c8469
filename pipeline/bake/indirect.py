"""What every indirect bake shares: the direct cache it extends, its chunk folder, its payloads.

An indirect bake (transfer, gather) first bakes the direct cache, then computes its own payloads
in resumable chunks kept in a hidden folder named after the content hash (so a changed shot or
setting never reuses stale chunks), and finally rewrites the cache layer with its method, its
parameters and all payloads.
"""

from __future__ import annotations

import dataclasses
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline import __version__
from pipeline.bake.direct import bake_direct, write_npy
from pipeline.scene.types import Camera, Scene
from relight_torch.cache.layer import CacheDescription, Payload, content_hash, read_cache_layer, write_cache_layer


@dataclass(frozen=True)
class IndirectBake:
    """An indirect bake in progress.

    Attributes:
        layer_path: the cache layer (the direct cache until `finish`).
        description: the direct cache's description.
        method: 'transfer' or 'gather'.
        parameters: the direct parameters plus the method's.
        content_hash: over the inputs and `parameters`.
        chunk_dir: where finished chunks are kept until `finish`.
    """

    layer_path: Path
    description: CacheDescription
    method: str
    parameters: dict
    content_hash: str
    chunk_dir: Path

    @property
    def out_dir(self) -> Path:
        return self.layer_path.parent

    def payload(self, stem: str, name: str, array: np.ndarray) -> Payload:
        """Write `<stem>.<name>.npy` beside the layer, atomically; its payload record."""
        return write_npy(self.out_dir / f"{stem}.{name}.npy", np.ascontiguousarray(array), name=name)

    def finish(self, payloads: list[Payload]) -> Path:
        """Rewrite the cache layer with the method's payloads, drop the chunks; the layer's path."""
        write_cache_layer(self.layer_path, dataclasses.replace(
            self.description, method=self.method, parameters=self.parameters, content_hash=self.content_hash,
            payloads=self.description.payloads + tuple(payloads)))
        shutil.rmtree(self.chunk_dir)
        return self.layer_path


def start_indirect_bake(scene: Scene, camera: Camera, out_dir: str | Path, stem: str, method: str,
                        method_parameters: dict, supersampling: int, texture_samples: int,
                        time_code: float | None) -> IndirectBake:
    """Bake the direct cache and prepare the chunk folder of an indirect method."""
    layer_path = bake_direct(scene, camera, Path(out_dir), stem, supersampling=supersampling,
                             texture_samples=texture_samples, time_code=time_code)
    description = read_cache_layer(layer_path)
    parameters = {**description.parameters, **method_parameters}
    digest = content_hash(description.inputs, parameters, __version__)
    chunk_dir = Path(out_dir) / f".{stem}.{method}-{digest[:16]}"
    chunk_dir.mkdir(parents=True, exist_ok=True)
    return IndirectBake(layer_path, description, method, parameters, digest, chunk_dir)
