"""Reference renders for the bench: one per (scene, light edit, bounce count), cached on disk.

Each image is `PathTracer(ReferenceSettings(spp, max_bounces=B, seed))` of the shot under the
edit's lights layer, saved as `<directory>/<stage>-<edit>-<W>x<H>-b<B>-spp<N>-seed<S>.npz`
(mean, variance, seconds; read back with allow_pickle=False), so a second bench run into the same
directory, and every method of one run, re-use it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.reference.path_tracer import PathTracer, ReferenceImage, ReferenceSettings
from pipeline.scene import find_camera, load_scene
from relight_torch.io.atomic import atomic_path


class References:
    """Lazily rendered, disk-cached reference images of one scene.

    Args:
        shot: the USD stage.
        camera: camera prim path.
        width, height: image size in pixels.
        edits: light edit name -> lights layer (None: the stage's lights).
        spp: reference samples per pixel.
        directory: where the .npz files go.
        seed: the reference's sampling seed.
    """

    def __init__(
        self,
        shot: Path,
        camera: str,
        width: int,
        height: int,
        edits: dict[str, Path | None],
        spp: int,
        directory: Path,
        seed: int = 0,
    ):
        self.shot, self.camera, self.width, self.height = shot, camera, width, height
        self.edits, self.spp, self.directory, self.seed = edits, spp, Path(directory), seed
        self._images: dict[tuple[str, int, int, int], ReferenceImage] = {}

    def path(self, edit: str, bounces: int, spp: int, seed: int) -> Path:
        return self.directory / f"{self.shot.stem}-{edit}-{self.width}x{self.height}-b{bounces}-spp{spp}-seed{seed}.npz"

    def render(
        self, edit: str, bounces: int, spp: int | None = None, seed: int | None = None, fresh: bool = False
    ) -> ReferenceImage:
        """The path tracer's image of `edit` with `bounces` indirect bounces.

        Args:
            spp, seed: default: the reference's (a render compared with the reference must use
                another seed, or their noise is correlated).
            fresh: render it again even when cached (the same image; its `seconds` then time this
                run, on this run's machine and load).
        """
        spp, seed = spp or self.spp, self.seed if seed is None else seed
        key = (edit, bounces, spp, seed)
        if fresh or key not in self._images:
            path = self.path(edit, bounces, spp, seed)
            if fresh or not path.is_file():
                scene = load_scene(self.shot, lights_layer=self.edits[edit], width=self.width, height=self.height)
                image = PathTracer(scene, ReferenceSettings(spp=spp, max_bounces=bounces, seed=seed)).render(
                    find_camera(scene, self.camera)
                )
                self.directory.mkdir(parents=True, exist_ok=True)
                with atomic_path(path) as temp, open(temp, "wb") as handle:
                    np.savez(
                        handle,
                        mean=image.mean,
                        variance=image.variance,
                        seconds=np.float64(image.seconds),
                        num_paths=np.int64(image.num_paths),
                        num_vertices=np.int64(image.num_vertices),
                    )
            with np.load(path, allow_pickle=False) as saved:
                self._images[key] = ReferenceImage(
                    saved["mean"],
                    saved["variance"],
                    float(saved["seconds"]),
                    int(saved["num_paths"]),
                    int(saved["num_vertices"]),
                )
        return self._images[key]

    def full(self, edit: str, bounces: int) -> np.ndarray:
        """(H, W, 3) float32 reference with `bounces` indirect bounces."""
        return self.render(edit, bounces).mean

    def indirect(self, edit: str, bounces: int) -> np.ndarray:
        """(H, W, 3) float32 indirect part: the `bounces`-bounce reference minus the 0-bounce one."""
        return self.full(edit, bounces) - self.full(edit, 0)
