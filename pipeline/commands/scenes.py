"""`relight scenes`: list the bundled test/demo scenes or write them (with example light edits)."""

from __future__ import annotations

import argparse
from pathlib import Path

from pipeline.errors import RelightError
from pipeline.scenes import LAYERED_SCENES, SCENES, layered_edit_layers, write_light_edits


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "scenes",
        help="list or write the bundled test/demo scenes",
        description="The project's bundled scenes (Cornell box, glossy materials, a large set), "
        "authored as USD by scripts in pipeline/scenes.",
    )
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    actions.add_parser("list", help="print each scene's name, camera prim and description")
    write = actions.add_parser(
        "write",
        help="write scenes as DIR/<name>.usda (+ textures/, + example light edits)",
        description="Write the bundled scenes into DIR as <name>.usda with textures under DIR/textures "
        "and example light-edit layers <name>.lights.<edit>.usda for --lights; a layered scene (glossy+dome) "
        "writes its base scene and the lights layer that adds its lights, its edits authored over that layer.",
    )
    write.add_argument("directory", metavar="DIR", help="output directory (created if missing)")
    write.add_argument(
        "--name",
        choices=sorted(SCENES) + sorted(LAYERED_SCENES),
        metavar="NAME",
        help=f"write only this scene ({', '.join([*SCENES, *LAYERED_SCENES])}; default: all)",
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    if args.action == "list":
        width = max(len(name) for name in [*SCENES, *LAYERED_SCENES])
        camera_width = max(len(scene.camera) for scene in SCENES.values())
        for name, scene in SCENES.items():
            print(f"{name:<{width}}  {scene.camera:<{camera_width}}  {scene.description}")
        for name, layered in LAYERED_SCENES.items():
            camera = SCENES[layered.base].camera
            print(f"{name:<{width}}  {camera:<{camera_width}}  {layered.description}")
        return 0
    directory = Path(args.directory)
    if directory.exists() and not directory.is_dir():
        raise RelightError(f"scenes write: {directory} exists and is not a directory")
    for name in [args.name] if args.name else [*SCENES, *LAYERED_SCENES]:
        if name in LAYERED_SCENES:
            layers = layered_edit_layers(name, directory)
            print(f"{name}: {directory / SCENES[LAYERED_SCENES[name].base].name}.usda --lights {layers.pop('shot')}")
            for path in layers.values():
                print(f"  --lights {path}")
            continue
        print(SCENES[name].write(directory))
        for path in write_light_edits(name, directory):
            print(f"  --lights {path}")
    return 0
