"""Sweep of the transfer method: kept coefficients x gather counts, against the reference.

    python -m pipeline.benchmarks.transfer_sweep SCENE [SCENE...] --width W --height H
        [--gathers 1024 4096 ...] [--coefficients 10 25 50 100 200] [--bounces B] [--spp N]
        [--quantize] [--rgb] [--indirect-scale S] [--out DIR]

Per scene and gather count it bakes once, keeping the largest coefficient count, and studies every
smaller count by culling those rows (`relight_torch.transfer.sparse.cull`, the bake's own order):
bake_s is that one bake's time for all of them (row evaluation dominates; culling takes < 1 %),
cache_bytes the bytes the layer's payloads take with the culled matrix written in full. Each point
is relit under the shot's lights and every example light edit and compared with
`PathTracer(max_bounces=B)`; the indirect part with the reference's B-bounce minus 0-bounce
images. relight_ms is the median time of a light move re-rendered (gather light, Haar transform,
sparse products and the direct part). One CSV row per (scene, gathers, coefficients, edit), the
columns shared with the other methods' sweeps.

With `--timing` it measures relight_ms alone at the given size (640 x 480 for the issue's target)
without the hours of F rows such a size costs: the real direct cache and gather cloud, and
synthetic F rows (every pixel's `--coefficients` distinct random indices and values), both
colour-factored and RGB; PSNR columns are empty. `--timing --cache LAYER...` times baked transfer
caches instead (real F rows; `--cull` and `--gather-samples` set the relighter's options), one
row for the whole edit (part=total: the direct relighter's re-render included) and one for the
indirect update alone (part=indirect: gather light, Haar, products, upsampling). `--cache LAYER...`
without `--timing` compares baked caches with the reference at their own size instead (the shot's
lights, `--spp` paths per pixel; how the 640 x 480 figures in docs/TRANSFER.md were taken).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import torch

from pipeline.bake.adapter import format_params
from pipeline.bake.direct.bake import bake_direct
from pipeline.bake.gather_cloud import create_gathers
from pipeline.bake.transfer.adapter import culled_variants
from pipeline.bake.transfer.bake import TransferSettings, bake_transfer
from pipeline.benchmarks.bench.measure import relight_ms
from pipeline.benchmarks.bench.references import References
from pipeline.benchmarks.rows import COLUMNS, NAN, SweepRow, csv_line
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES, light_edit_layers
from relight_torch.cache.layer import CacheDescription
from relight_torch.direct.loading import shot_lights
from relight_torch.direct.relighter import open_relighter
from relight_torch.metrics import psnr, rel_mse
from relight_torch.transfer.open import open_transfer_relighter
from relight_torch.transfer.relighter import GATHER_SAMPLES, TransferRelighter
from relight_torch.transfer.sparse import SparseRows


def sweep_scene(name: str, args: argparse.Namespace, directory: Path) -> None:
    """Print the CSV rows of one scene."""
    bundled = SCENES[name]
    shot = bundled.write(directory)
    layers = light_edit_layers(name, directory)
    refs = References(shot, bundled.camera, args.width, args.height, layers, args.spp, directory / "references")
    expected = {edit: (refs.full(edit, args.bounces), refs.indirect(edit, args.bounces)) for edit in layers}
    scene = load_scene(shot, width=args.width, height=args.height)
    camera = find_camera(scene, bundled.camera)
    for num_gathers in args.gathers:
        settings = TransferSettings(
            num_gathers=num_gathers,
            num_coefficients=max(args.coefficients),
            num_bounces=args.bounces,
            encoding="uint8" if args.quantize else "float16",
            factor_colour=not args.rgb,
            indirect_scale=args.indirect_scale,
        )
        cache = directory / f"cache-{num_gathers}"
        start = time.perf_counter()
        layer = bake_transfer(
            scene, camera, cache, name, args.supersampling, args.texture_samples, settings=settings, progress=False
        )
        bake_s = time.perf_counter() - start
        relighter = open_transfer_relighter(layer, shadows=args.shadows)
        description = relighter.direct.description
        for variant in culled_variants(layer, relighter, settings, sorted(args.coefficients)):
            point, params = variant.relighter, format_params(variant.parameters)
            for edit, layer_path in layers.items():
                point.set_lights(shot_lights(description, layer_path))
                image, indirect = point.render().numpy(), point.indirect_image().numpy()
                full, reference_indirect = expected[edit]
                timing = relight_ms(point) if edit == "shot" else NAN
                print(
                    csv_line(
                        SweepRow(
                            "transfer",
                            name,
                            args.width,
                            args.height,
                            edit,
                            params,
                            psnr(image, full),
                            psnr(indirect, reference_indirect),
                            rel_mse(image, full),
                            variant.cache_bytes,
                            bake_s,
                            timing,
                        )
                    ),
                    flush=True,
                )


def synthetic_rows(num_rows: int, num_columns: int, num_kept: int, factored: bool, seed: int = 0) -> SparseRows:
    """Random `SparseRows` of the given size (what the timing costs depends on, not the values)."""
    generator = torch.Generator().manual_seed(seed)
    # One random index per stratum of num_columns / num_kept columns: sorted and unique per row.
    stratum = num_columns // num_kept
    indices = torch.arange(num_kept) * stratum + torch.randint(stratum, (num_rows, num_kept), generator=generator)
    channels = 1 if factored else 3
    values = torch.rand((num_rows * num_kept, channels), generator=generator) * 1e-3
    colour = torch.rand((num_rows, 3), generator=generator) if factored else None
    offsets = torch.arange(num_rows + 1, dtype=torch.int64) * num_kept
    return SparseRows(values, indices.reshape(-1).to(torch.int32), offsets, num_columns, colour)


def time_scene(name: str, args: argparse.Namespace, directory: Path) -> None:
    """Print relight_ms rows of one scene at the given size with synthetic F rows."""
    bundled = SCENES[name]
    shot = bundled.write(directory)
    scene = load_scene(shot, width=args.width, height=args.height)
    layer = bake_direct(
        scene, find_camera(scene, bundled.camera), directory / "cache", name, args.supersampling, args.texture_samples
    )
    direct = open_relighter(layer, shadows=args.shadows)
    view_pixels = torch.arange(args.width * args.height)
    for num_gathers in args.gathers:
        gathers = create_gathers(scene, num_gathers)
        for factored in (True, False):
            rows = synthetic_rows(view_pixels.shape[0], num_gathers, max(args.coefficients), factored)
            relighter = TransferRelighter(direct, gathers, view_pixels, rows.to("cpu", torch.float32))
            relighter.render()
            params = format_params(
                {
                    "gathers": num_gathers,
                    "coefficients": max(args.coefficients),
                    "rowColour": int(factored),
                    "synthetic": 1,
                }
            )
            print(
                csv_line(
                    SweepRow(
                        "transfer",
                        name,
                        args.width,
                        args.height,
                        "shot",
                        params,
                        cache_bytes=rows.num_bytes,
                        relight_ms=relight_ms(relighter, repeats=7),
                    )
                ),
                flush=True,
            )


def _transfer_parameters(description: CacheDescription) -> dict[str, object]:
    """The transfer bake's own parameters of a cache layer (`TransferSettings.parameters` keys)."""
    return {key: description.parameters[key] for key in TransferSettings(indirect_scale=1).parameters()}


def time_caches(args: argparse.Namespace) -> None:
    """Print a part=total and a part=indirect relight_ms row per baked transfer cache."""
    for layer in args.cache:
        relighter = open_transfer_relighter(layer, shadows=args.shadows, cull_tolerance=args.cull)
        relighter.gather_samples = args.gather_samples
        description = relighter.direct.description
        height, width = (size // relighter.direct.supersampling for size in relighter.direct.gbuffer.image_size)
        parameters = {
            **_transfer_parameters(description),
            "cull": args.cull,
            "gatherSamples": args.gather_samples,
            "threads": torch.get_num_threads(),
        }
        cache_bytes = sum(p.num_bytes for p in description.payloads)
        relighter.render()
        for part, method in (("total", "render"), ("indirect", "indirect_image")):
            print(
                csv_line(
                    SweepRow(
                        "transfer",
                        Path(description.source).stem,
                        width,
                        height,
                        "shot",
                        format_params({**parameters, "part": part}),
                        cache_bytes=cache_bytes,
                        relight_ms=relight_ms(relighter, repeats=7, part=method),
                    )
                ),
                flush=True,
            )


def accuracy_caches(args: argparse.Namespace) -> None:
    """Print a row per baked transfer cache: PSNR of the full and indirect images under the shot's
    lights against `PathTracer` references at the cache's own size (`--spp` paths)."""
    for layer in args.cache:
        relighter = open_transfer_relighter(layer, shadows=args.shadows, cull_tolerance=args.cull)
        description = relighter.direct.description
        width, height = description.resolution
        refs = References(
            Path(description.source),
            description.camera_path,
            width,
            height,
            {"shot": None},
            args.spp,
            Path(layer).parent / "references",
        )
        full, reference_indirect = (
            refs.full("shot", relighter.num_bounces),
            refs.indirect("shot", relighter.num_bounces),
        )
        image, indirect = relighter.render().numpy(), relighter.indirect_image().numpy()
        params = format_params({**_transfer_parameters(description), "cull": args.cull, "spp": args.spp})
        print(
            csv_line(
                SweepRow(
                    "transfer",
                    Path(description.source).stem,
                    width,
                    height,
                    "shot",
                    params,
                    psnr(image, full),
                    psnr(indirect, reference_indirect),
                    rel_mse(image, full),
                    sum(p.num_bytes for p in description.payloads),
                )
            ),
            flush=True,
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes", nargs="+", choices=sorted(SCENES))
    parser.add_argument("--width", type=int, default=64)
    parser.add_argument("--height", type=int, default=64)
    parser.add_argument("--gathers", type=int, nargs="+", default=[1024, 4096])
    parser.add_argument("--coefficients", type=int, nargs="+", default=[10, 25, 50, 100, 200])
    parser.add_argument("--bounces", type=int, default=1)
    parser.add_argument("--spp", type=int, default=512, help="reference samples per pixel")
    parser.add_argument("--supersampling", type=int, default=2)
    parser.add_argument("--texture-samples", type=int, default=2)
    parser.add_argument("--shadows", default="embree", choices=("embree", "shadowmaps"))
    parser.add_argument("--quantize", action="store_true", help="8-bit coefficients")
    parser.add_argument("--rgb", action="store_true", help="RGB coefficients instead of one colour per row")
    parser.add_argument(
        "--indirect-scale",
        type=int,
        help="F for an image this many times smaller per side (default: sized from the image)",
    )
    parser.add_argument("--timing", action="store_true", help="relight_ms only, synthetic F rows")
    parser.add_argument(
        "--cache",
        nargs="+",
        metavar="LAYER",
        help="baked transfer caches: their accuracy against the reference at their size (--spp), "
        "or with --timing their relight times",
    )
    parser.add_argument(
        "--cull", type=float, default=0.0, help="with --cache: culling tolerance of weak wavelet lights"
    )
    parser.add_argument(
        "--gather-samples",
        type=int,
        default=GATHER_SAMPLES,
        help=f"with --cache: light samples per gather (default {GATHER_SAMPLES})",
    )
    parser.add_argument("--out", help="directory for the scenes and caches (default: a temporary one)")
    args = parser.parse_args(argv)
    directory = Path(args.out or tempfile.mkdtemp(prefix="relight-transfer-sweep-"))
    print(",".join(COLUMNS), flush=True)
    if args.cache:
        (time_caches if args.timing else accuracy_caches)(args)
        return 0
    for name in args.scenes:
        (time_scene if args.timing else sweep_scene)(name, args, directory / name)
    return 0


if __name__ == "__main__":
    sys.exit(main())
