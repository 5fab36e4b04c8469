"""`relight serve`'s page in a real browser: Debian's chromium driven by Playwright through its system
executable. The page loads and shows frames, a slider drag changes the displayed frame, the
material panel edits a material, a click places the selected light, and save writes a layer that
`relight render` turns into the page's last frame. Without /usr/bin/chromium these tests fail,
naming the package (`.ci/run` installs it)."""

from __future__ import annotations

import contextlib
import io

import numpy as np
import pytest
from PIL import Image

from pipeline.benchmarks.browser import CHROMIUM, WAIT_MS, chromium_page
from pipeline.cli import main as relight_main
from pipeline.serve.app import create_app
from pipeline.serve.display import png_bytes
from pipeline.serve.placement import SurfaceLookup
from pipeline.serve.server import serving
from pipeline.serve.session import Session
from relight_torch.cache.layer import read_cache_layer
from relight_torch.cache.load import load_gbuffer
from relight_torch.io.exr import read_rgb_exr
from serve_support import TOKEN, bake

RENDER_TOLERANCE = 1e-3
# The displayed frame's pixels, read back through a canvas (the page's own <img>).
PIXELS_JS = """() => { const img = document.getElementById('frame'); const c = document.createElement('canvas');
  c.width = img.naturalWidth; c.height = img.naturalHeight; const g = c.getContext('2d'); g.drawImage(img, 0, 0);
  return Array.from(g.getImageData(0, 0, c.width, c.height).data); }"""


@contextlib.contextmanager
def page_at(url: str):
    if not CHROMIUM.is_file():  # CI installs chromium: its absence is a failure, not a skip
        pytest.fail(f"{CHROMIUM} is missing: install Debian's 'chromium' package (apt-get install chromium)")
    with chromium_page(url) as page:
        yield page


@pytest.fixture(scope="module")
def layer(tmp_path_factory):
    return bake(tmp_path_factory.mktemp("serve_browser_bake"))


@pytest.fixture
def served(layer, tmp_path):
    session = Session.open(layer, out_dir=tmp_path)
    try:
        with serving(create_app(session, TOKEN)) as base, page_at(f"{base}/?token={TOKEN}") as page:
            yield page, session
    finally:
        session.close()


def displayed(page) -> np.ndarray:
    rgba = np.array(page.evaluate(PIXELS_JS), np.int32)
    return rgba.reshape(32, 32, 4)[..., :3]


def wait_for_version_after(page, version: int) -> int:
    """Wait until the page shows the final (converged) frame of a version after `version`."""
    page.wait_for_function(
        f"window.relight.displayedVersion > {version} && window.relight.displayedFinal", timeout=WAIT_MS
    )
    return int(page.evaluate("window.relight.displayedVersion"))


def test_page_loads_with_the_lights_and_a_frame(served):
    page, session = served
    assert page.locator("#lights .light").count() == len(session.state()["lights"])
    assert page.evaluate("document.getElementById('frame').naturalWidth") == 32
    assert displayed(page).sum() > 0


def test_slider_drag_changes_the_displayed_frame(served):
    page, session = served
    before, version = displayed(page), page.evaluate("window.relight.displayedVersion")
    slider = page.locator('#attributes [data-attribute="inputs:intensity"] input[type=range]')
    box = slider.bounding_box()
    page.mouse.move(box["x"] + box["width"] * 0.3, box["y"] + box["height"] / 2)
    page.mouse.down()
    for step in range(1, 6):  # a drag towards the right end: brighter
        page.mouse.move(box["x"] + box["width"] * (0.3 + 0.12 * step), box["y"] + box["height"] / 2)
    page.mouse.up()
    page.wait_for_function(
        f"window.relight.displayedVersion >= {session.version} && window.relight.displayedFinal", timeout=WAIT_MS
    )
    assert page.evaluate("window.relight.displayedVersion") > version
    after = displayed(page)
    assert after.sum() > before.sum()
    assert session.state()["canUndo"]


def test_the_material_panel_edits_a_material(served):
    page, session = served
    material = page.evaluate("document.getElementById('material-select').value")
    assert material in session.state()["materialPaths"]
    before, version = displayed(page), page.evaluate("window.relight.displayedVersion")
    picker = page.locator('#material-inputs [data-input="inputs:diffuseColor"] input[type=color]')
    picker.fill("#00ff00")  # an input and a change event, as a colour chosen in the picker
    wait_for_version_after(page, version)
    page.wait_for_function(
        f"window.relight.displayedVersion >= {session.version} && window.relight.displayedFinal", timeout=WAIT_MS
    )
    assert session.state()["materials"][material]["inputs:diffuseColor"] == [0.0, 1.0, 0.0]
    assert np.abs(displayed(page) - before).max() > 0


def test_click_places_the_selected_light(served, layer):
    page, session = served
    path = session.state()["lights"][0]["path"]
    page.select_option("#click-mode", "normal")
    page.fill("#distance", "0.25")
    version = page.evaluate("window.relight.displayedVersion")
    box = page.locator("#frame").bounding_box()
    x, y = 8, 24  # pixel centres of the 32x32 frame, whatever its size on screen
    page.mouse.click(box["x"] + (x + 0.5) * box["width"] / 32, box["y"] + (y + 0.5) * box["height"] / 32)
    wait_for_version_after(page, version)
    description = read_cache_layer(layer)
    point = SurfaceLookup(load_gbuffer(layer, description), description.supersampling).at(x, y)
    light = next(light for light in session.state()["lights"] if light["path"] == path)
    position = np.array(light["attributes"]["xformOp:transform"])[3, :3]
    np.testing.assert_allclose(position, point.position + 0.25 * point.normal, atol=1e-9)


def test_save_writes_a_layer_that_renders_the_last_frame(served, layer, tmp_path):
    page, session = served
    page.select_option("#add-type", "SphereLight")
    version = page.evaluate("window.relight.displayedVersion")
    page.click("#add")
    version = wait_for_version_after(page, version)
    number = page.locator('#attributes [data-attribute="inputs:exposure"] input[type=number]')
    number.fill("1.5")
    number.dispatch_event("change")
    wait_for_version_after(page, version)
    page.fill("#save-path", "from_page.usda")
    page.click("#save")
    page.wait_for_function("document.getElementById('saved').textContent.includes('SphereLight')", timeout=WAIT_MS)
    saved = tmp_path / "from_page.usda"
    assert saved.is_file()
    frame = next(iter(session.frames())).image
    assert relight_main(["render", str(layer), "--lights", str(saved), "-o", str(tmp_path / "render.exr")]) == 0
    assert np.abs(read_rgb_exr(tmp_path / "render.exr") - frame).max() <= RENDER_TOLERANCE
    # What the page shows is that frame through the display transform.
    shown = np.asarray(Image.open(io.BytesIO(png_bytes(frame))).convert("RGB"), np.int32)
    np.testing.assert_array_equal(displayed(page), shown)


def wait_for_frames_after(page, frames: int) -> None:
    page.wait_for_function(f"window.relight.frames > {frames}", timeout=WAIT_MS)


def test_exposure_group_view_and_the_light_buttons(served):
    page, session = served
    before, frames = displayed(page), page.evaluate("window.relight.frames")
    page.locator("#exposure").fill("1")
    wait_for_frames_after(page, frames)
    brighter = displayed(page)
    assert brighter.sum() > before.sum()
    count = page.locator("#lights .light").count()
    version = page.evaluate("window.relight.displayedVersion")
    page.select_option("#add-type", "DiskLight")
    page.click("#add")
    version = wait_for_version_after(page, version)
    page.wait_for_function(f"document.querySelectorAll('#lights .light').length === {count + 1}", timeout=WAIT_MS)
    group = session.state()["lights"][-1]["group"]
    frames = page.evaluate("window.relight.frames")
    page.select_option("#view-select", f"group:{group}")
    wait_for_frames_after(page, frames)
    page.wait_for_function(
        f"document.getElementById('status').textContent.startsWith('version {version}')", timeout=WAIT_MS
    )
    groups = next(iter(session.frames(groups=True))).groups
    shown = np.asarray(Image.open(io.BytesIO(png_bytes(groups[group], exposure=1.0))).convert("RGB"), np.int32)
    np.testing.assert_array_equal(displayed(page), shown)
    page.click("#remove")
    page.wait_for_function(f"document.querySelectorAll('#lights .light').length === {count}", timeout=WAIT_MS)
    page.click("#undo")
    page.wait_for_function(f"document.querySelectorAll('#lights .light').length === {count + 1}", timeout=WAIT_MS)
    assert [light["path"] for light in session.state()["lights"]][-1].endswith("DiskLight1")
