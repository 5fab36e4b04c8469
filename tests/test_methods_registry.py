"""The method registry and the relighter protocol (STYLE.md rule 13).

Every registered method: its relight- and bake-side entries agree; its relighter satisfies
`CacheRelighter` (isinstance, then every member called on a tiny cache); its packages import no
sibling method's package beyond what it declares in `builds_on`.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import textwrap

import pytest
import torch

from pipeline.bake.methods import BakeMethod, bake_method, bake_methods
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES
from relight_torch import open_cache
from relight_torch.errors import RelightError
from relight_torch.methods import METHOD_NAMES, relight_method, relight_methods
from relight_torch.progressive import progressive_frames
from relight_torch.protocol import CacheRelighter

SIZE = 24


def test_every_name_has_one_relight_and_one_bake_entry():
    assert tuple(relight_methods()) == METHOD_NAMES == tuple(bake_methods())
    for name in METHOD_NAMES:
        entry = bake_method(name)
        assert entry.relight is relight_method(name)
        assert entry.name == entry.adapter.name == name
        assert entry.ladder and entry.stability_point and entry.default_supersampling >= 1
        assert set(entry.relight.builds_on) <= set(METHOD_NAMES) - {name}


def test_unknown_method_is_one_error_line():
    with pytest.raises(RelightError, match=r"no relighting method 'nope'.*direct"):
        relight_method("nope")


def test_a_view_capability_needs_a_view_renderer():
    entry = bake_method("direct")
    relight = dataclasses.replace(entry.relight, needs_view=True)
    with pytest.raises(ValueError, match="render_views"):
        dataclasses.replace(entry, relight=relight)


def test_bake_choices_and_option_groups_come_from_the_registry(capsys):
    from pipeline.cli import build_parser

    parser = build_parser()
    for name in METHOD_NAMES:
        args = parser.parse_args(["bake", "shot.usda", "--camera", "/World/Camera", "--out", "o", "--method", name])
        assert args.method == name
    with pytest.raises(SystemExit):
        parser.parse_args(["bake", "shot.usda", "--camera", "/World/Camera", "--out", "o", "--method", "nope"])
    capsys.readouterr()
    with pytest.raises(SystemExit):
        parser.parse_args(["bake", "--help"])
    text = capsys.readouterr().out
    assert all(f"{name} (--method {name})" in text for name in METHOD_NAMES if name != "direct")


_ISOLATION = textwrap.dedent("""
    import importlib, json, pkgutil, sys
    name, others = sys.argv[1], sys.argv[2].split(",")
    for root in ("relight_torch", "pipeline.bake"):
        package = importlib.import_module(f"{root}.{name}")
        for module in pkgutil.walk_packages(package.__path__, f"{root}.{name}."):
            importlib.import_module(module.name)
    print(json.dumps(sorted(module for module in sys.modules
                            for other in others for root in ("relight_torch", "pipeline.bake")
                            if module == f"{root}.{other}" or module.startswith(f"{root}.{other}."))))
""")


@pytest.mark.slow
@pytest.mark.parametrize("name", METHOD_NAMES)
def test_method_packages_import_no_sibling_method(name):
    """Each method's packages (`relight_torch.<name>`, `pipeline.bake.<name>`), every module
    imported in a fresh interpreter, load no other method's package but those it builds on."""
    forbidden = [other for other in METHOD_NAMES if other != name and other not in relight_method(name).builds_on]
    result = subprocess.run(
        [sys.executable, "-c", _ISOLATION, name, ",".join(forbidden)], capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout.splitlines()[-1]) == []


@pytest.mark.slow
def test_isolation_check_sees_a_sibling_import():
    """The check above fails when a method package imports a sibling (here: cuts, made to)."""
    result = subprocess.run(
        [
            sys.executable,
            "-c",
            _ISOLATION.replace(
                "import importlib, json, pkgutil, sys",
                "import importlib, json, pkgutil, sys\nimport relight_torch.cuts.open",
            ),
            "transfer",
            "cuts",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    assert "relight_torch.cuts.open" in json.loads(result.stdout.splitlines()[-1])


def _bake(name: str, root) -> tuple[BakeMethod, dict[str, object], object]:
    """The entry, its first quick bench point and that point's cache layer (Cornell box, SIZE x SIZE)."""
    shot = SCENES["cornell_box"].write(root / "scene")
    scene = load_scene(shot, width=SIZE, height=SIZE)
    camera = find_camera(scene, SCENES["cornell_box"].camera)
    entry = bake_method(name)
    point = entry.adapter.grid(True)[0]
    return entry, point, entry.adapter.bake(scene, camera, root, "cornell_box", point, 1, 1)


@pytest.mark.slow
@pytest.mark.parametrize("name", METHOD_NAMES)
def test_every_relighter_satisfies_the_protocol(tmp_path, name):
    entry, point, layer = _bake(name, tmp_path)
    if not entry.relight.needs_view:
        opened = open_cache(layer)
        assert isinstance(opened, CacheRelighter)
        assert type(opened) is type(entry.adapter.variants(layer, point, "cpu")[0].relighter)
    relighter = entry.adapter.variants(layer, point, "cpu")[0].relighter  # a view set where one is needed
    assert isinstance(relighter, CacheRelighter)

    lights = relighter.lights
    assert lights
    image = relighter.render()
    assert image.shape == (SIZE, SIZE, 3) and bool(torch.isfinite(image).all()) and float(image.sum()) > 0
    groups = relighter.light_group_images()
    emission = relighter.emission_image()
    assert emission.shape == image.shape
    torch.testing.assert_close(sum(groups.values()) + emission, image, rtol=1e-4, atol=1e-5)
    assert isinstance(relighter.held_bytes(), int) and relighter.held_bytes() > 0

    brighter = dataclasses.replace(lights[0], intensity=2 * lights[0].intensity)
    relighter.set_light(brighter)
    assert float(relighter.render().sum()) > float(image.sum())
    relighter.remove_light(lights[0].path)
    assert [light.path for light in relighter.lights] == [light.path for light in lights[1:]]
    relighter.set_lights(lights)
    torch.testing.assert_close(relighter.render(), image, rtol=1e-4, atol=1e-6)

    if relighter.material_edits:
        relighter.edit_material(0, roughness=0.9)
        assert relighter.render().shape == image.shape
    else:
        with pytest.raises(RelightError, match="re-bake after a material edit"):
            relighter.edit_material(0, roughness=0.9)

    edits = relighter.edits
    relighter.set_light(brighter)
    assert relighter.edits > edits
    if relighter.progressive:  # tests/test_progressive.py checks it edit by edit
        frames = list(progressive_frames(relighter, budget_ms=0.0))
        assert frames[-1].done and len(frames) > 1
        torch.testing.assert_close(frames[-1].image, relighter.render(), rtol=0.0, atol=1e-6)
    else:
        with pytest.raises(RelightError, match="no progressive refinement"):
            relighter.refine(None)
