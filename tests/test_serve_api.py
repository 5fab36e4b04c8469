"""`relight serve`'s HTTP and WebSocket API (docs/SERVE.md) through Starlette's TestClient: the token,
the Origin check, edits and their refusals, undo, placement, save and load, views, and a bounded fuzz
of malformed requests (each a 4xx; the TestClient raises on any server error)."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import httpx2
import hypothesis
import numpy as np
import pytest
from hypothesis import strategies as st
from PIL import Image
from starlette.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from pipeline.cli import main as relight_main
from pipeline.serve.app import create_app
from pipeline.serve.display import png_bytes
from pipeline.serve.placement import SurfaceLookup
from pipeline.serve.session import Frame, Session
from pipeline.serve.stream import FrameStream
from relight_torch import open_cache
from relight_torch.cache.layer import read_cache_layer
from relight_torch.cache.load import load_gbuffer
from relight_torch.io.exr import read_rgb_exr, write_rgb_exr
from serve_support import AUTH, TOKEN, bake, client

RENDER_TOLERANCE = 1e-3
"""Largest |session frame - `relight render` frame| allowed (the issue's bound; float32 sums taken in
another light order differ by ~1e-7)."""


@pytest.fixture(scope="module")
def layer(tmp_path_factory):
    return bake(tmp_path_factory.mktemp("serve_bake"))


@pytest.fixture
def served(layer, tmp_path):
    with client(layer, tmp_path) as pair:
        yield pair


def first_light(test_client) -> dict:
    return test_client.get("/api/lights", headers=AUTH).json()["lights"][0]


def exr_frame(test_client) -> np.ndarray:
    response = test_client.get("/api/frame.exr", headers=AUTH)
    assert response.status_code == 200
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "frame.exr"
        path.write_bytes(response.content)
        return read_rgb_exr(path)


def png_pixels(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"), np.int32)


def test_every_request_needs_the_token(served):
    test_client, _ = served
    for path in ("/", "/api/lights", "/api/session", "/api/frame.png"):
        assert test_client.get(path).status_code == 401
        assert test_client.get(path, headers={"Authorization": "Bearer wrong"}).status_code == 401
        assert test_client.get(f"{path}?token=wrong").status_code == 401
    assert test_client.get(f"/?token={TOKEN}").status_code == 200
    assert "<title>relight serve</title>" in test_client.get(f"/?token={TOKEN}").text
    assert test_client.get("/api/lights", headers=AUTH).status_code == 200
    with pytest.raises(WebSocketDisconnect), test_client.websocket_connect("ws://127.0.0.1:8000/api/frames") as socket:
        socket.receive_json()


def test_websocket_from_a_foreign_origin_is_refused(served):
    test_client, _ = served
    for origin in ("http://evil.example:8000", "http://127.0.0.1:9999", "null", "file://"):
        with (
            pytest.raises(WebSocketDisconnect) as refused,
            test_client.websocket_connect(
                f"ws://127.0.0.1:8000/api/frames?token={TOKEN}", headers={"Origin": origin}
            ) as socket,
        ):
            socket.receive_json()
        assert refused.value.code == 4403
    with test_client.websocket_connect(
        f"ws://127.0.0.1:8000/api/frames?token={TOKEN}", headers={"Origin": "http://127.0.0.1:8000"}
    ) as socket:
        header = socket.receive_json()
        assert header["type"] == "frame"
        assert png_pixels(socket.receive_bytes()).shape == (32, 32, 3)


def test_a_server_on_every_interface_takes_same_origin_websockets_by_any_name(layer, tmp_path):
    session = Session.open(layer, out_dir=tmp_path)
    try:
        with TestClient(create_app(session, TOKEN, hosts=None), base_url="http://10.1.2.3:8000") as test_client:
            url = f"ws://10.1.2.3:8000/api/frames?token={TOKEN}"
            with test_client.websocket_connect(url, headers={"Origin": "http://10.1.2.3:8000"}) as socket:
                assert socket.receive_json()["type"] == "frame"
            with (
                pytest.raises(WebSocketDisconnect),
                test_client.websocket_connect(url, headers={"Origin": "http://evil.example:8000"}) as socket,
            ):
                socket.receive_json()
    finally:
        session.close()


def test_an_edit_changes_the_frame_and_bad_values_are_refused(served):
    test_client, _ = served
    light = first_light(test_client)
    before = exr_frame(test_client)
    url = f"/api/lights{light['path']}"
    intensity = light["attributes"]["inputs:intensity"]
    response = test_client.patch(url, json={"inputs:intensity": 2 * intensity}, headers=AUTH)
    assert response.status_code == 200, response.text
    after = exr_frame(test_client)
    np.testing.assert_allclose(after, 2 * before, rtol=1e-4, atol=1e-6)  # intensity is linear in the image
    sphere = test_client.post("/api/lights", json={"type": "SphereLight"}, headers=AUTH).json()["path"]
    refusals = {
        (url, '{"inputs:intensity": NaN}'): "must be finite",
        (url, '{"inputs:intensity": -1}'): ">= 0",
        (f"/api/lights{sphere}", '{"inputs:radius": -0.5}'): ">= 0",
        (url, '{"inputs:nonsense": 1}'): "no such attribute",
        (url, '{"inputs:color": [1, 2]}'): "3 numbers",
        (url, '{"inputs:intensity": 1e999}'): "must be finite",
    }
    for (target, body), message in refusals.items():
        response = test_client.patch(target, content=body, headers=AUTH | {"Content-Type": "application/json"})
        assert response.status_code == 400, (body, response.text)
        assert message in response.json()["error"] and "\n" not in response.json()["error"]
    response = test_client.patch("/api/lights/World/NoSuchLight", json={"inputs:intensity": 1}, headers=AUTH)
    assert response.status_code == 404 and "no light" in response.json()["error"]
    np.testing.assert_allclose(exr_frame(test_client), after + _sphere_image(test_client, sphere, after), atol=1e-6)


def _sphere_image(test_client, sphere, without_sphere):
    """The image the added sphere adds (muting it gives the rest)."""
    full = exr_frame(test_client)
    test_client.patch(f"/api/lights{sphere}", json={"muted": True}, headers=AUTH)
    rest = exr_frame(test_client)
    np.testing.assert_allclose(rest, without_sphere, atol=1e-6)
    test_client.patch(f"/api/lights{sphere}", json={"muted": False}, headers=AUTH)
    return full - rest


def test_undo_redo_and_gestures(served):
    test_client, _ = served
    light = first_light(test_client)
    url = f"/api/lights{light['path']}"
    start = exr_frame(test_client)
    for value in (1.0, 2.0, 3.0):  # one drag: one undo step
        test_client.patch(f"{url}?gesture=drag1", json={"inputs:exposure": value}, headers=AUTH)
    test_client.patch(url, json={"inputs:color": [1.0, 0.5, 0.25]}, headers=AUTH)
    assert test_client.post("/api/undo", headers=AUTH).status_code == 200
    assert first_light(test_client)["attributes"]["inputs:exposure"] == 3.0
    assert test_client.post("/api/undo", headers=AUTH).status_code == 200
    assert first_light(test_client)["attributes"]["inputs:exposure"] == light["attributes"]["inputs:exposure"]
    np.testing.assert_array_equal(exr_frame(test_client), start)
    assert test_client.post("/api/undo", headers=AUTH).status_code == 400  # nothing left
    assert test_client.post("/api/redo", headers=AUTH).status_code == 200
    assert first_light(test_client)["attributes"]["inputs:exposure"] == 3.0


def test_enable_mute_solo_and_light_groups(served):
    test_client, session = served
    lights = test_client.get("/api/lights", headers=AUTH).json()
    full = exr_frame(test_client)
    added = test_client.post("/api/lights", json={"type": "DiskLight"}, headers=AUTH).json()["path"]
    with_disk = exr_frame(test_client)
    assert with_disk.sum() > full.sum()
    test_client.patch(f"/api/lights{added}", json={"soloed": True}, headers=AUTH)
    solo = exr_frame(test_client)
    np.testing.assert_allclose(solo, with_disk - full, atol=1e-5)
    group = test_client.get("/api/lights", headers=AUTH).json()["lights"][-1]["group"]
    response = test_client.get(f"/api/frame.png?view=group:{group}", headers=AUTH)
    assert response.status_code == 200
    assert test_client.get("/api/frame.png?view=group:nope", headers=AUTH).status_code == 400
    assert test_client.get("/api/frame.png?view=reference", headers=AUTH).status_code == 400  # no --reference
    test_client.patch(f"/api/lights{added}", json={"soloed": False, "enabled": False}, headers=AUTH)
    np.testing.assert_allclose(exr_frame(test_client), full, atol=1e-6)
    assert "active = false" not in session.save_text()  # a new light, disabled: nothing to save of it
    test_client.patch(f"/api/lights{lights['lights'][0]['path']}", json={"enabled": False}, headers=AUTH)
    assert "active = false" in session.save_text()  # a light of the shot, disabled: deactivated


def test_click_places_along_the_normal_and_aims(served, layer):
    test_client, _ = served
    path = first_light(test_client)["path"]
    description = read_cache_layer(layer)
    lookup = SurfaceLookup(load_gbuffer(layer, description), description.supersampling)
    point = lookup.at(10, 20)
    response = test_client.post(
        "/api/place", json={"path": path, "x": 10, "y": 20, "mode": "normal", "distance": 0.3}, headers=AUTH
    )
    assert response.status_code == 200, response.text
    world_from_light = np.array(first_light(test_client)["attributes"]["xformOp:transform"]).T
    np.testing.assert_allclose(world_from_light[:3, 3], point.position + 0.3 * point.normal, atol=1e-9)
    minus_z = -world_from_light[:3, 2] / np.linalg.norm(world_from_light[:3, 2])
    np.testing.assert_allclose(minus_z, -point.normal, atol=1e-9)
    target = lookup.at(25, 5)
    assert test_client.post("/api/place", json={"path": path, "x": 25, "y": 5}, headers=AUTH).status_code == 200
    aimed = np.array(first_light(test_client)["attributes"]["xformOp:transform"]).T
    np.testing.assert_allclose(aimed[:3, 3], world_from_light[:3, 3], atol=1e-12)  # aiming turns in place
    towards = target.position - aimed[:3, 3]
    np.testing.assert_allclose(
        -aimed[:3, 2] / np.linalg.norm(aimed[:3, 2]), towards / np.linalg.norm(towards), atol=1e-9
    )
    for body in (
        {"path": path, "x": 32, "y": 0},
        {"path": path, "x": 1.5, "y": 0},
        {"path": path, "x": 0, "y": 0, "mode": "x"},
    ):
        assert test_client.post("/api/place", json=body, headers=AUTH).status_code == 400


def test_saved_layer_renders_the_session_frame(served, layer, tmp_path):
    """Save -> `relight render CACHE --lights SAVED` equals the session's last frame within 1e-3."""
    test_client, _ = served
    lights = test_client.get("/api/lights", headers=AUTH).json()["lights"]
    test_client.patch(
        f"/api/lights{lights[0]['path']}", json={"inputs:intensity": 0.5, "inputs:color": [1, 0.8, 0.6]}, headers=AUTH
    )
    added = test_client.post("/api/lights", json={"type": "SphereLight"}, headers=AUTH).json()["path"]
    test_client.post(
        "/api/place", json={"path": added, "x": 16, "y": 28, "mode": "normal", "distance": 0.2}, headers=AUTH
    )
    test_client.patch(
        f"/api/lights{added}",
        json={"inputs:colorTemperature": 3000, "inputs:enableColorTemperature": True},
        headers=AUTH,
    )
    if len(lights) > 1:
        test_client.delete(f"/api/lights{lights[1]['path']}", headers=AUTH)
    response = test_client.post("/api/save", json={"path": "session.usda"}, headers=AUTH)
    assert response.status_code == 200, response.text
    saved = tmp_path / "session.usda"
    assert saved.read_text() == response.json()["text"]
    frame = exr_frame(test_client)
    assert relight_main(["render", str(layer), "--lights", str(saved), "-o", str(tmp_path / "render.exr")]) == 0
    rendered = read_rgb_exr(tmp_path / "render.exr")
    assert np.abs(rendered - frame).max() <= RENDER_TOLERANCE
    # Load brings the saved rig back after more edits.
    test_client.patch(f"/api/lights{added}", json={"inputs:intensity": 100.0}, headers=AUTH)
    assert test_client.post("/api/load", json={"path": "session.usda"}, headers=AUTH).status_code == 200
    np.testing.assert_allclose(exr_frame(test_client), frame, atol=RENDER_TOLERANCE)
    assert test_client.post("/api/load", json={"text": saved.read_text()}, headers=AUTH).status_code == 200


def test_a_session_opened_with_a_lights_layer_saves_against_the_shot(layer, tmp_path):
    """--lights LAYER edits are part of the session's rig: a layer saved at once holds them, since
    `relight render --lights SAVED` composes SAVED over the shot alone."""
    edits = tmp_path / "edits.usda"
    edits.write_text(
        '#usda 1.0\nover "World"\n{\n    over "Lights"\n    {\n        over "CeilingLight"\n'
        "        {\n            float inputs:intensity = 5\n        }\n    }\n}\n"
    )
    with client(layer, tmp_path, lights=edits) as (test_client, _):
        frame = exr_frame(test_client)
        saved = test_client.post("/api/save", json={"path": "saved.usda"}, headers=AUTH).json()
    assert "float inputs:intensity = 5" in saved["text"]
    assert relight_main(["render", str(layer), "--lights", str(edits), "-o", str(tmp_path / "edits.exr")]) == 0
    assert relight_main(["render", str(layer), "--lights", saved["path"], "-o", str(tmp_path / "saved.exr")]) == 0
    np.testing.assert_allclose(read_rgb_exr(tmp_path / "edits.exr"), frame, atol=RENDER_TOLERANCE)
    np.testing.assert_allclose(read_rgb_exr(tmp_path / "saved.exr"), frame, atol=RENDER_TOLERANCE)


def test_client_paths_stay_in_the_output_directory(served, tmp_path):
    test_client, _ = served
    outside = tmp_path.parent / f"{tmp_path.name}-outside.usda"
    (tmp_path / "link").symlink_to(tmp_path.parent)
    for path in ("../x.usda", str(outside), "link/x.usda", "/etc/passwd", "", "x.txt", "missing/x.usda"):
        response = test_client.post("/api/save", json={"path": path}, headers=AUTH)
        assert response.status_code == 400, (path, response.text)
    assert not outside.exists()
    for path in ("../x.usda", "/etc/passwd", "link/x.usda", "nope.usda"):
        assert test_client.post("/api/load", json={"path": path}, headers=AUTH).status_code == 400
    sublayer = "#usda 1.0\n(\n    subLayers = [@/etc/hosts@]\n)\n"
    response = test_client.post("/api/load", json={"text": sublayer}, headers=AUTH)
    assert response.status_code == 400 and "sublayers" in response.json()["error"]
    texture = '#usda 1.0\ndef DomeLight "D"\n{\n    asset inputs:texture:file = @/etc/hosts@\n}\n'
    assert test_client.post("/api/load", json={"text": texture}, headers=AUTH).status_code == 400
    path = first_light(test_client)["path"]
    response = test_client.patch(f"/api/lights{path}", json={"inputs:texture:file": "/etc/hosts"}, headers=AUTH)
    assert response.status_code == 400


def test_reference_view_and_psnr(layer, tmp_path):
    with client(layer, tmp_path) as (test_client, _):
        image = exr_frame(test_client)
    write_rgb_exr(tmp_path / "ref.exr", image * 0.5)
    with client(layer, tmp_path, reference=tmp_path / "ref.exr") as (test_client, _):
        reference = png_pixels(test_client.get("/api/frame.png?view=reference", headers=AUTH).content)
        beauty = png_pixels(test_client.get("/api/frame.png", headers=AUTH).content)
        assert reference.sum() < beauty.sum()
        with test_client.websocket_connect(f"ws://127.0.0.1:8000/api/frames?token={TOKEN}") as socket:
            header = socket.receive_json()
            socket.receive_bytes()
        assert header["psnr"] is not None and header["psnr"] > 10


LIGHT = "/api/lights/World/Lights/CeilingLight"
MALFORMED = [
    ("PATCH", LIGHT, b"{not json"),
    ("PATCH", LIGHT, b"[1, 2]"),
    ("PATCH", LIGHT, b"{}"),
    ("PATCH", LIGHT, b'{"inputs:intensity": "1"}'),
    ("PATCH", LIGHT, b'{"inputs:intensity": true}'),
    ("PATCH", LIGHT, b'{"inputs:intensity": 1' + b"0" * 400 + b"}"),
    ("PATCH", LIGHT, b'{"inputs:intensity": -Infinity}'),
    ("PATCH", LIGHT, b'{"xformOp:transform": [[1e300, 0, 0, 0]]}'),
    (
        "PATCH",
        "/api/lights/World/Lights/CeilingLight",
        b'{"xformOp:transform": [[0,0,0,0],[0,0,0,0],[0,0,0,0],[0,0,0,1]]}',
    ),
    ("PATCH", LIGHT, b'{"enabled": "yes"}'),
    ("PATCH", LIGHT, b'{"relight:lightGroup": 5}'),
    ("PATCH", LIGHT, b'{"ShapingAPI": 1}'),
    (
        "PATCH",
        "/api/lights/World/Lights/CeilingLight",
        b'{"relight:barzel:near:start": 5, "relight:barzel:near:end": 1}',
    ),
    ("PATCH", "/api/lights/" + "x" * 5000, b'{"inputs:intensity": 1}'),
    ("PATCH", "/api/lights/", b'{"inputs:intensity": 1}'),
    ("DELETE", "/api/lights/World/Nothing", b""),
    ("POST", "/api/lights", b'{"type": "MeshLight"}'),
    ("POST", "/api/lights", b'{"type": "SphereLight", "path": "not a path"}'),
    ("POST", "/api/lights", b'{"type": "SphereLight", "path": "/World/Lights/CeilingLight"}'),
    ("POST", "/api/lights", b'{"type": "SphereLight", "attributes": [1]}'),
    ("POST", "/api/place", b'{"path": "/World/Lights/CeilingLight", "x": -1, "y": 0}'),
    ("POST", "/api/place", b'{"path": "/World/Lights/CeilingLight", "x": 0, "y": 0, "distance": -1}'),
    ("POST", "/api/place", b'{"x": 0, "y": 0}'),
    ("POST", "/api/save", b'{"path": 5}'),
    ("POST", "/api/load", b"{}"),
    ("POST", "/api/load", b'{"text": "not usd at all"}'),
    ("POST", "/api/load", b'{"text": "#usda 1.0\\ndef SphereLight \\"S\\" { float inputs:radius = -1 }"}'),
    ("GET", "/api/frame.png?exposure=nan", b""),
    ("GET", "/api/frame.png?exposure=1e400", b""),
    ("GET", "/api/frame.png?view=../../etc", b""),
    ("GET", "/api/nothing", b""),
    ("PUT", "/api/lights", b"{}"),
]


def test_malformed_requests_are_4xx_and_the_session_goes_on(served):
    test_client, _ = served
    for method, path, body in MALFORMED:
        response = test_client.request(method, path, content=body, headers=AUTH | {"Content-Type": "application/json"})
        assert 400 <= response.status_code < 500, (method, path, body[:80], response.status_code, response.text)
        assert isinstance(response.json()["error"], str), (method, path)
    assert test_client.get("/api/frame.png", headers=AUTH).status_code == 200


def test_fuzzed_edits_are_4xx_or_applied(served):
    """Random attribute names and JSON values: each edit is applied (2xx) or refused (4xx), never a crash."""
    test_client, _ = served
    path = first_light(test_client)["path"]
    names = st.sampled_from(
        ["inputs:intensity", "inputs:color", "inputs:radius", "inputs:width", "xformOp:transform", "muted", "bogus"]
    )
    scalars = st.none() | st.booleans() | st.floats() | st.integers(-(10**30), 10**30) | st.text(max_size=8)
    values = scalars | st.lists(scalars, max_size=5) | st.lists(st.lists(scalars, max_size=5), max_size=5)

    @hypothesis.settings(max_examples=60, deadline=None, derandomize=True)
    @hypothesis.given(st.dictionaries(names, values, max_size=3))
    def edit(body):
        text = json.dumps(body, allow_nan=True)
        response = test_client.patch(f"/api/lights{path}", content=text, headers=AUTH)
        assert response.status_code < 500, (text, response.text)

    edit()
    assert test_client.get("/api/frame.png", headers=AUTH).status_code == 200


def test_two_clients_editing_at_once(served):
    """Two clients editing different lights concurrently, each watching frames: both edits land and
    the last final frame both see is the final rig's."""
    test_client, _ = served
    first = first_light(test_client)["path"]
    second = test_client.post("/api/lights", json={"type": "RectLight"}, headers=AUTH).json()["path"]
    errors: list[str] = []

    def drag(path: str, name: str) -> None:
        for step in range(15):
            response = test_client.patch(f"/api/lights{path}", json={name: 0.5 + 0.1 * step}, headers=AUTH)
            if response.status_code != 200:
                errors.append(response.text)

    with (
        test_client.websocket_connect(f"ws://127.0.0.1:8000/api/frames?token={TOKEN}") as one,
        test_client.websocket_connect(f"ws://127.0.0.1:8000/api/frames?token={TOKEN}") as two,
    ):
        threads = [
            threading.Thread(target=drag, args=(first, "inputs:exposure")),
            threading.Thread(target=drag, args=(second, "inputs:intensity")),
        ]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        final = test_client.get("/api/lights", headers=AUTH).json()
        expected = exr_frame(test_client)
        for socket in (one, two):
            header = {"version": -1, "final": False}
            while header["version"] < final["version"] or not header["final"]:  # coarse frames come first
                header = socket.receive_json()
                pixels = png_pixels(socket.receive_bytes())
            assert header["version"] == final["version"]
    assert not errors
    values = {light["path"]: light["attributes"] for light in final["lights"]}
    assert values[first]["inputs:exposure"] == pytest.approx(1.9)
    assert values[second]["inputs:intensity"] == pytest.approx(1.9)
    np.testing.assert_array_equal(pixels, png_pixels(png_bytes(expected)))


class _SlowSession:
    """A stand-in session whose frames wait for the test's go, to check coalescing deterministically."""

    def __init__(self):
        self.changed = threading.Condition()
        self.version = 0
        self.go = threading.Event()
        self.rendered: list[int] = []

    def frames(self, groups=False):
        with self.changed:
            version = self.version
        self.go.wait(10)
        self.rendered.append(version)
        yield Frame(version, np.zeros((1, 1, 3), np.float32))


def test_edits_made_while_rendering_coalesce_into_the_latest():
    session = _SlowSession()
    stream = FrameStream(session)
    stream.start()
    try:
        for _ in range(5):  # version 0 renders (blocked); versions 1..5 arrive meanwhile
            with session.changed:
                session.version += 1
                session.changed.notify_all()
        session.go.set()
        frame = stream.wait_frame(timeout=10)
        assert frame.version == 5
        assert session.rendered in ([0, 5], [5])  # never the stale versions 1..4
    finally:
        stream.stop()


def test_the_command_prints_a_tokened_loopback_url_and_serves(layer, tmp_path):
    process = subprocess.Popen(
        [sys.executable, "-m", "pipeline.cli", "serve", str(layer), "--out", str(tmp_path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=os.environ | {"PYTHONPATH": os.pathsep.join(sys.path)},
    )
    try:
        line = process.stdout.readline()
        url = urlsplit(line.split(": ", 2)[-1].strip())
        assert url.hostname == "127.0.0.1" and url.port, line
        token = parse_qs(url.query)["token"][0]
        assert len(token) >= 32
        base = f"http://127.0.0.1:{url.port}"
        assert httpx2.get(f"{base}/api/lights", timeout=30).status_code == 401
        response = httpx2.get(f"{base}/api/lights", headers={"Authorization": f"Bearer {token}"}, timeout=30)
        assert response.status_code == 200 and response.json()["lights"]
    finally:
        process.terminate()
        process.wait(30)


def test_the_command_refuses_bad_arguments_in_one_line(layer, tmp_path, capsys):
    assert relight_main(["serve", str(tmp_path / "missing.relight.usda")]) == 2
    assert relight_main(["serve", str(layer), "--port", "70000"]) == 2
    assert relight_main(["serve", str(layer), "--out", str(tmp_path / "nowhere")]) == 2
    errors = capsys.readouterr().err.strip().splitlines()
    assert len(errors) == 3 and all(line.startswith("relight: error: ") for line in errors)


def test_malformed_websocket_messages_are_answered_and_the_stream_goes_on(served):
    test_client, _ = served
    with test_client.websocket_connect(f"ws://127.0.0.1:8000/api/frames?token={TOKEN}") as socket:
        header = {"type": "frame", "final": False}
        while not header["final"]:  # the first version's coarse frames, then its converged one
            header = socket.receive_json()
            assert header["type"] == "frame"
            socket.receive_bytes()
        for message in ("not json", "[1]", '{"type": "other"}', '{"type": "display", "exposure": "NaN"}'):
            socket.send_text(message)
            assert socket.receive_json()["type"] == "error", message
        socket.send_bytes(b"\x00\x01")
        assert socket.receive_json()["type"] == "error"
        socket.send_text('{"type": "display", "exposure": 2}')
        header = socket.receive_json()
        assert header["type"] == "frame" and header["exposure"] == 2
        assert png_pixels(socket.receive_bytes()).shape == (32, 32, 3)


def test_an_edit_streams_coarse_frames_then_the_exact_one(layer, tmp_path):
    # The direct cache refines progressively: coarse frames first, the last one final and equal to
    # a freshly opened relighter's render of the saved rig.
    session = Session.open(layer, out_dir=tmp_path)
    try:
        light = session.state()["lights"][0]
        session.edit(light["path"], {"inputs:intensity": 3 * light["attributes"]["inputs:intensity"]})
        frames = list(session.frames())
        assert len(frames) > 1 and [f.final for f in frames] == [False] * (len(frames) - 1) + [True]
        assert {f.version for f in frames} == {session.version}
        (tmp_path / "saved.usda").write_text(session.save_text())
        fresh = open_cache(layer, lights_layer=tmp_path / "saved.usda").render().numpy()
        np.testing.assert_allclose(frames[-1].image, fresh, rtol=0, atol=1e-6)
    finally:
        session.close()
