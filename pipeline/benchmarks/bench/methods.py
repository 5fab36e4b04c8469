"""`BenchScene`, what the bench hands every method, and the methods' adapters from the registry.

The adapter protocol (`pipeline.bake.adapter.MethodAdapter`) and each method's adapter live on the
bake side, beside each bake (`pipeline/bake/<method>/adapter.py`), registered as `BakeMethod.adapter`
(`pipeline.bake.methods`). `measure.run_point` bakes one point for a `BenchScene` and measures every
variant under every light edit (`measure.relit_rows`); the stability suite and the quality sizing
call `bake` and `variants` directly on their own scenes and lights. Adapters never render references.

Adding a method is registering it (`relight_torch.methods`): the bench, its chart and its tests
pick it up.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from pipeline.bake.adapter import MethodAdapter
from pipeline.bake.methods import bake_methods
from pipeline.benchmarks.bench.references import References
from pipeline.scene import find_camera, load_scene
from pipeline.scene.types import Camera, Scene


@dataclass(frozen=True)
class BenchScene:
    """What the runner prepares once per bundled scene and hands every adapter.

    Attributes:
        name: bundled scene name (`pipeline.scenes.SCENES`).
        shot: the written USD stage.
        camera: prim path of the camera to bake and render.
        width, height: image size in pixels.
        edits: light edit name -> lights layer ('shot' -> None: the stage's own lights).
        directory: where this scene's caches go (an adapter makes its own subdirectory).
        device: torch device the relighters run on ('cpu', 'cuda').
        repeats: timed light edits per relight_ms median.
        references: the reference images, rendered on first use and cached.
        supersampling, texture_samples: of every method's direct part (not swept, so that the
            methods differ in what they add; the direct adapter sweeps supersampling).
    """

    name: str
    shot: Path
    camera: str
    width: int
    height: int
    edits: dict[str, Path | None]
    directory: Path
    device: str
    repeats: int
    references: References
    supersampling: int = 2
    texture_samples: int = 2

    def load(self) -> tuple[Scene, Camera]:
        """The stage at the bench size, under its own lights, and the camera."""
        scene = load_scene(self.shot, width=self.width, height=self.height)
        return scene, find_camera(scene, self.camera)

    def cache_dir(self, method: str, point: dict[str, object]) -> Path:
        """`directory / '<method>-<key>-<value>-...'`: one cache directory per bake configuration."""
        parts = [method] + [
            f"{key}-{'_'.join(map(str, value)) if isinstance(value, tuple) else value}" for key, value in point.items()
        ]
        return self.directory / "-".join(parts)


def adapters(names: list[str] | tuple[str, ...] | None = None) -> dict[str, MethodAdapter]:
    """name -> ADAPTER of the registered methods (all of them, or those named, in registry order).

    Raises:
        ValueError: a name is not registered.
    """
    registered = {name: method.adapter for name, method in bake_methods().items()}
    unknown = sorted(set(names or ()) - set(registered))
    if unknown:
        raise ValueError(f"unknown method(s) {unknown}; registered: {list(registered)}")
    return {name: adapter for name, adapter in registered.items() if names is None or name in names}
