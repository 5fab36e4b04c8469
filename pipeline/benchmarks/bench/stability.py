"""The stability suite: where each relighting method is known to fail, measured, not hidden.

    python -m pipeline.benchmarks.bench.stability [--out docs/STABILITY.md] [--width 32 --height 32 --spp 64]

Each `StabilityCase` sets up one hard situation on a bundled scene (lights placed in Python, the
stage's geometry optionally changed in memory), and for each method it names (the keys of `why`)
bakes that method's small stability point (`BakeMethod.stability_point`, overridden per case), relights under the
case's lights and compares with the path tracer at the method's bounce count (same lights, same
geometry). `tests/test_stability.py` asserts every image is finite and its PSNR at least the
case's `min_psnr` (the measured value less a margin: an honest bound, not a target);
`write_doc` writes docs/STABILITY.md with the measured table and one sentence per case and
method on why the method fails there.

Adding a method: add its sentence to the `why` of the cases that apply to it and its bound to
`min_psnr` (its stability point is its registry entry's, `pipeline.bake.methods`); a case that only
makes sense for one method is a new `StabilityCase` in CASES (cuts: 'dome_short_cuts'). A case
judged from another camera than the baked one (multiview: 'far_camera') sets `view` (baked camera ->
the camera to judge from); the runner then renders with `adapter.relight_view(variant, camera)`,
which only the adapters that support novel views define. Cases run in CASES order and share bakes,
so a `view` case comes after the cases judged from the baked camera.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.bake.adapter import MethodAdapter, Variant, format_params
from pipeline.bake.methods import bake_method
from pipeline.benchmarks.bench.methods import adapters
from pipeline.benchmarks.direct import look_at
from pipeline.reference.path_tracer import PathTracer, ReferenceSettings
from pipeline.scene import find_camera, load_scene
from pipeline.scene.types import Camera, Scene
from pipeline.scenes import SCENES
from relight_torch.io.atomic import write_text_atomic
from relight_torch.lights.light import Light, LightKind, Shaping
from relight_torch.metrics import psnr, rel_mse

UP = np.array([0.0, 1.0, 0.0])


@dataclass(frozen=True)
class StabilityCase:
    """One hard situation.

    Attributes:
        name: short id (the table's row).
        scene: bundled scene name.
        description: what is set up, one line.
        lights: the scene (as loaded, before `geometry`) -> the case's lights.
        why: method -> one sentence on why the method fails (or holds) there; the methods run.
        min_psnr: method -> the PSNR bound the tests assert (dB).
        geometry: the loaded scene -> the scene to bake and render (None: unchanged).
        points: method -> bake-point overrides of its `stability_point`.
        view: the baked camera -> the camera the image is judged from (None: the baked one).
    """

    name: str
    scene: str
    description: str
    lights: Callable[[Scene], list[Light]]
    why: dict[str, str]
    min_psnr: dict[str, float]
    geometry: Callable[[Scene], Scene] | None = None
    points: dict[str, dict[str, object]] = field(default_factory=dict)
    view: Callable[[Camera], Camera] | None = None

    def point(self, method: str) -> dict[str, object]:
        return {**bake_method(method).stability_point, **self.points.get(method, {})}


@dataclass(frozen=True)
class CaseResult:
    """What one (case, method) measured: PSNR and relMSE against the reference, finiteness."""

    case: str
    method: str
    params: str
    psnr_db: float
    rel_mse: float
    finite: bool
    bounces: int


def _lamp(scene: Scene) -> Light:
    return scene.lights[0]


def _placed(light: Light, position, target, scale: float = 1.0, **changes) -> Light:
    """`light` moved to `position`, its -Z aimed at `target`, its intensity times `scale`."""
    world_from_light = look_at(np.asarray(position, float), np.asarray(target, float), UP)
    return dataclasses.replace(light, world_from_light=world_from_light, intensity=light.intensity * scale, **changes)


def _object_triangles(scene: Scene, name: str) -> np.ndarray:
    """(T,) bool: the triangles of the object whose prim path ends with '/name'."""
    ids = [i for i, obj in enumerate(scene.objects) if obj.path.endswith("/" + name)]
    if not ids:
        raise ValueError(f"no object named {name!r} in {scene.source}")
    return np.isin(scene.geometry.object_ids, ids)


def _object_centre(scene: Scene, name: str) -> np.ndarray:
    return scene.geometry.positions[_object_triangles(scene, name)].reshape(-1, 3).mean(axis=0).astype(float)


def _bad_normals(scene: Scene) -> Scene:
    """Cornell box with the tall block's shading normals flipped and the short block's zero."""
    normals = scene.geometry.normals.copy()
    normals[_object_triangles(scene, "TallBlock")] *= -1.0
    normals[_object_triangles(scene, "ShortBlock")] = 0.0
    return dataclasses.replace(scene, geometry=dataclasses.replace(scene.geometry, normals=normals))


def _close_corner(scene: Scene) -> list[Light]:
    # A 20 mm square lamp 20 mm from the floor, the green wall and the back wall, same power.
    lamp = _lamp(scene)
    return [
        _placed(
            lamp, (20.0, 20.0, 539.2), (278.0, 274.0, 280.0), lamp.width * lamp.height / 400.0, width=20.0, height=20.0
        )
    ]


def _tight_spot(scene: Scene) -> list[Light]:
    # The lamp as a 5-degree spot at 200x intensity from the ceiling onto the back wall: a patch
    # about 70 mm across, saturated, lighting the room as a small strong secondary source.
    lamp = _lamp(scene)
    return [_placed(lamp, (278.0, 540.0, 280.0), (278.0, 150.0, 559.2), 200.0, shaping=Shaping(cone_angle=5.0))]


def _grazing(scene: Scene) -> list[Light]:
    # A 130 x 10 mm strip 8 mm above the floor at the front, aimed along it (about 1 degree).
    lamp = _lamp(scene)
    return [_placed(lamp, (278.0, 8.0, 5.0), (278.0, 0.0, 559.2), lamp.height / 10.0, height=10.0)]


def _inside_block(scene: Scene) -> list[Light]:
    # The lamp, plus a bright 20 mm sphere light inside the (closed) tall block.
    hidden = Light(
        "/Stability/Hidden",
        LightKind.SPHERE,
        look_at(_object_centre(scene, "TallBlock"), np.zeros(3), UP),
        intensity=200.0,
        radius=20.0,
        color=(1.0, 1.0, 1.0),
    )
    return [_lamp(scene), hidden]


def _shot(scene: Scene) -> list[Light]:
    return list(scene.lights)


def _far_camera(camera: Camera) -> Camera:
    """A camera in the box's upper front-left corner aimed at the far lower-right corner: far from
    every caching camera, seeing the blocks' sides and the floor behind them at new angles."""
    return dataclasses.replace(
        camera,
        world_from_camera=look_at(np.array([40.0, 520.0, 30.0]), np.array([450.0, 0.0, 520.0]), UP),
        path="/Stability/FarCamera",
    )


CASES: list[StabilityCase] = [
    StabilityCase(
        "baseline",
        "cornell_box",
        "the shot's own lamp: what the other Cornell cases are compared with",
        _shot,
        why={
            "direct": "Nothing hard: the error is the reference's own noise (64 spp) and one sub-sample per pixel.",
            "transfer": "Nothing hard: the error adds 1024 gathers and 50 kept coefficients to the direct part's.",
            "gather": "Nothing hard: the error adds 16 clusters of 256 directions at 64 representatives.",
            "multiview": (
                "Nothing hard: the baked camera's view is rebuilt from the caching cameras' deep "
                "framebuffers (128-pixel caching images here), adding their resampling to the direct "
                "relighter's error."
            ),
        },
        min_psnr={"direct": 29.0, "transfer": 30.0, "gather": 29.0, "multiview": 36.5},
    ),
    StabilityCase(
        "close_corner",
        "cornell_box",
        "a 20 mm lamp 20 mm from three walls in a corner (1/r^2 at close range)",
        _close_corner,
        why={
            "direct": "Next to the lamp irradiance changes by orders of magnitude within a pixel, and one "
            "sub-sample per pixel misses it (the 2 x 2 direct part of transfer and gather has about a "
            "quarter of this error); the close lamp also subtends a large solid angle for 16 samples.",
            "transfer": "The indirect light is right on average (within a few per cent); its error is on the "
            "walls beside the lamp, where few of the 1024 gathers see the 1/r^2 peak.",
            "gather": "Clusters average D over gather points whose irradiance differs by orders of magnitude "
            "next to the lamp: the bounce comes out 10-20 % too weak.",
        },
        min_psnr={"direct": 25.0, "transfer": 28.0, "gather": 26.0},
    ),
    StabilityCase(
        "tight_spot",
        "cornell_box",
        "a 5-degree spot at 200x intensity making a small bright patch on the back wall",
        _tight_spot,
        why={
            "direct": "The relighter takes a few light samples on the 130 x 105 mm lamp and with a 5-degree "
            "cone each sample lights its own small ellipse, so the spot breaks into blobs.",
            "transfer": "The bright patch is carried by the few gathers that land in it, each standing for "
            "its whole cell: the indirect light is about a quarter too strong and blotchy, worst on "
            "the ceiling the patch lights.",
            "gather": "16 clusters at 64 representatives miss the patch's gather points almost altogether: "
            "nearly all of the indirect light it casts is lost (with 4x the representatives, about a "
            "quarter), worst on the ceiling the patch lights.",
        },
        min_psnr={"direct": 21.0, "transfer": 17.0, "gather": 17.0},
    ),
    StabilityCase(
        "grazing",
        "cornell_box",
        "a strip light 8 mm above the floor aimed along it (about 1 degree incidence)",
        _grazing,
        why={
            "direct": "The error sits in the bottom image row: the floor within a few centimetres of the strip "
            "is lit at 1/r^2 at grazing incidence, and one sub-sample per pixel misses the bright "
            "sliver that the path tracer's pixel average includes.",
            "transfer": "It shares the direct part's bottom-row error, and the floor's gathers next to the strip "
            "are lit at 1/r^2, so a few gathers carry a badly sampled share of the bounce: the "
            "indirect light is about a quarter too strong.",
            "gather": "It shares the direct part's bottom-row error, and its indirect light is about 75 % too "
            "strong: the few representatives near the strip gather points lit at 1/r^2, and the "
            "radial-basis weights spread that over the floor.",
        },
        min_psnr={"direct": 16.0, "transfer": 15.0, "gather": 15.0},
    ),
    StabilityCase(
        "inside_geometry",
        "cornell_box",
        "the lamp plus a bright sphere light inside the closed tall block",
        _inside_block,
        why={
            "direct": "Holds (PSNR equals the baseline's): every shadow ray towards the hidden light hits "
            "the block, so it adds nothing; shadow maps would leak where their depth bias exceeds "
            "the block's wall thickness, which a closed block does not have.",
            "transfer": "Holds (within noise of the baseline): gathers on the block's inner faces are lit, "
            "but transfer rows are traced with visibility, so no outer pixel sees them.",
            "gather": "Holds (within noise of the baseline): gather points are found by tracing from "
            "visible points, so the inner faces are never gathered.",
        },
        min_psnr={"direct": 29.0, "transfer": 31.0, "gather": 30.0},
    ),
    StabilityCase(
        "bad_normals",
        "cornell_box",
        "tall block's shading normals flipped, short block's zero",
        _shot,
        geometry=_bad_normals,
        why={
            "direct": "Holds to within about 1 dB, no NaN: zero normals fall back to the face normal in the "
            "shared tracing layer on both sides (the short block's error is unchanged); the extra error "
            "is on the flipped tall block (twice the baseline's there), whose back-facing shading "
            "normal the relighter and the path tracer resolve differently.",
            "transfer": "Loses a few dB, no NaN: the zero normals fall back to the face normal as in the path "
            "tracer, but the flipped tall block's error grows about 20x: its final-gather rows are "
            "evaluated with the flipped normal, so the block's indirect light comes from the wrong "
            "hemisphere.",
            "gather": "Loses a few dB, no NaN: the zero normals fall back to the face normal as in the path "
            "tracer, but the flipped tall block's representatives gather around the flipped normal "
            "and that block's error grows about 10x.",
        },
        min_psnr={"direct": 28.0, "transfer": 28.0, "gather": 27.0},
    ),
    StabilityCase(
        "glossy_few_coefficients",
        "glossy",
        "glossy scene with 10 wavelet coefficients / 4 clusters",
        _shot,
        points={"transfer": {"coefficients": 10}, "gather": {"clusters": 4}},
        why={
            "direct": "The normal-mapped bricks are finer than a pixel: one sub-sample per pixel cannot "
            "average the reflected highlights the path tracer integrates.",
            "transfer": "Glossy transport is high-frequency in light space, and 10 kept Haar coefficients "
            "per row keep only its coarsest blocks.",
            "gather": "A glossy lobe needs many directions, and 4 clusters per representative average "
            "them into a diffuse-looking reflection.",
        },
        min_psnr={"direct": 21.0, "transfer": 23.0, "gather": 23.0},
    ),
    StabilityCase(
        "dome_cut_256",
        "dome",
        "glossy scene under the textured dome, illumination cut 256 (the default)",
        _shot,
        why={
            "cuts": (
                "Near the 64-spp reference's own noise under a textured dome at one sub-sample per pixel; "
                "the rest is the BRDF evaluated once per merged cluster, at its mean direction, which blurs "
                "the metals' sharp reflections of the dome."
            )
        },
        min_psnr={"cuts": 25.5},
    ),
    StabilityCase(
        "dome_short_cuts",
        "dome",
        "the same with an illumination cut of 16 clusters",
        _shot,
        points={"cuts": {"cut": 16}},
        why={
            "cuts": (
                "16 illumination clusters merge the dome's bright regions with dark ones and each cluster's "
                "light arrives from its mean direction: glossy reflections of the dome lose their shape "
                "and shadows soften, about 3.5 dB below a cut of 256."
            )
        },
        min_psnr={"cuts": 22.0},
    ),
    StabilityCase(
        "far_camera",
        "cornell_box",
        "the shot judged from a camera 0.9 m right of the baked one, outside the box",
        _shot,
        view=_far_camera,
        why={
            "multiview": (
                "From the corner the blocks' sides and the floor behind them are seen at angles no caching "
                "camera had, or not at all: those pixels are resampled from coarse, oblique caching "
                "pixels or stay holes (hole baking is off here), about 8 dB below the baseline."
            )
        },
        min_psnr={"multiview": 28.5},
    ),
]


class StabilityRun:
    """Runs cases at one size; bakes are shared between cases with the same scene and point.

    Args:
        directory: scratch directory (stages, caches).
        width, height: image size.
        spp: reference samples per pixel.
        device: torch device of the relighters.
    """

    def __init__(self, directory: Path, width: int = 32, height: int = 32, spp: int = 64, device: str = "cpu"):
        self.directory, self.width, self.height, self.spp, self.device = Path(directory), width, height, spp, device
        self._adapters = adapters()
        self._variants: dict[tuple, tuple[Scene, Camera, Variant]] = {}

    def _bake(
        self, case: StabilityCase, adapter: MethodAdapter, point: dict[str, object]
    ) -> tuple[Scene, Camera, Variant]:
        key = (case.scene, case.geometry, adapter.name, format_params({k: str(v) for k, v in point.items()}))
        if key not in self._variants:
            bundled = SCENES[case.scene]
            shot = self.directory / "scenes" / case.scene / f"{case.scene}.usda"
            if not shot.is_file():
                bundled.write(shot.parent)
            scene = load_scene(shot, width=self.width, height=self.height)
            camera = find_camera(scene, bundled.camera)
            if case.geometry is not None:
                scene = case.geometry(scene)
            directory = self.directory / "caches" / f"{case.name}-{adapter.name}"
            directory.mkdir(parents=True, exist_ok=True)
            layer = adapter.bake(scene, camera, directory, case.scene, point, 2, 2)
            (variant,) = adapter.variants(layer, point, self.device)
            self._variants[key] = (scene, camera, variant)
        return self._variants[key]

    def measure(self, case: StabilityCase, method: str) -> CaseResult:
        """Bake (or re-use), relight under the case's lights, compare with the path tracer."""
        adapter = self._adapters[method]
        point = case.point(method)
        scene, camera, variant = self._bake(case, adapter, point)
        lights = case.lights(scene)
        bounces = adapter.bounces(point)
        if case.view is None:
            variant.relighter.set_lights(lights)
            image = variant.relighter.render().cpu().numpy()
        else:
            camera = case.view(camera)
            variant.relighter.set_lights(lights)
            image = adapter.relight_view(variant, camera).cpu().numpy()
        reference = (
            PathTracer(
                dataclasses.replace(scene, lights=list(lights)), ReferenceSettings(spp=self.spp, max_bounces=bounces)
            )
            .render(camera)
            .mean
        )
        return CaseResult(
            case.name,
            method,
            format_params(variant.parameters),
            psnr(image, reference),
            rel_mse(image, reference),
            bool(np.isfinite(image).all()),
            bounces,
        )

    def run(self, cases: list[StabilityCase] = CASES) -> list[CaseResult]:
        return [self.measure(case, method) for case in cases for method in case.why]


def write_doc(results: list[CaseResult], path: Path, command: str, cases: list[StabilityCase] = CASES) -> None:
    """docs/STABILITY.md: the measured table and one sentence per case and method."""
    by_case = {case.name: case for case in cases}
    lines = [
        "# Stability: where each method fails, measured",
        "",
        "Generated by `pipeline/benchmarks/bench/stability.py`; `tests/test_stability.py` runs the same cases",
        "and asserts every image is finite and its PSNR at least the bound (the measured value less a",
        "margin, not a target). The reference is the path tracer at the method's bounce count (direct: 0,",
        "transfer and gather: 1), same lights and geometry. Small sizes: these are the failure modes' ",
        "signatures, not the methods' accuracy at production sizes (see the bench for those).",
        "",
        f"    {command}",
        "",
        "| case | method | params | PSNR dB | bound dB | relMSE | finite |",
        "|---|---|---|---|---|---|---|",
    ]
    for result in results:
        case = by_case[result.case]
        lines.append(
            f"| {result.case} | {result.method} | {result.params} | {result.psnr_db:.2f} | "
            f"{case.min_psnr[result.method]:.0f} | {result.rel_mse:.3g} | {'yes' if result.finite else 'NO'} |"
        )
    lines += ["", "## Why each method fails there", ""]
    for case in cases:
        lines += [f"### {case.name}: {case.description}", ""]
        lines += [f"- **{method}**: {sentence}" for method, sentence in case.why.items()]
        lines.append("")
    lines += [
        "## Adding a method or a case",
        "",
        "A method joins a case by adding its sentence to the case's `why` and its bound to `min_psnr` (its",
        "small bake point is its registry entry's `stability_point`). A case for one method is a new",
        "`StabilityCase` (cuts: `dome_short_cuts`); one judged from another camera than the baked one",
        "(multiview: `far_camera`) sets `view`, and the method's adapter then provides",
        "`relight_view(variant, camera)`.",
        "",
    ]
    write_text_atomic(path, "\n".join(lines))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="docs/STABILITY.md", help="the Markdown file to write")
    parser.add_argument("--work", default=None, help="scratch directory (default: a temporary one)")
    parser.add_argument("--width", type=int, default=32)
    parser.add_argument("--height", type=int, default=32)
    parser.add_argument("--spp", type=int, default=64)
    args = parser.parse_args(argv)
    import tempfile

    with tempfile.TemporaryDirectory(prefix="relight-stability-") as scratch:
        results = StabilityRun(Path(args.work or scratch), args.width, args.height, args.spp).run()
    for result in results:
        print(
            f"{result.case:24s} {result.method:9s} {result.psnr_db:6.2f} dB  relMSE {result.rel_mse:.3g}"
            f"{'' if result.finite else '  NOT FINITE'}",
            flush=True,
        )
    command = (
        "python -m pipeline.benchmarks.bench.stability --out docs/STABILITY.md "
        f"--width {args.width} --height {args.height} --spp {args.spp}"
    )
    write_doc(results, Path(args.out), command)
    return 0 if all(math.isfinite(r.psnr_db) or r.psnr_db == math.inf for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
