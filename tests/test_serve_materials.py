"""`relight serve`'s material edits (PATCH /api/materials/<prim>): frames, undo, the saved layer
that `relight render --materials` reads back, loading it, and the refusals."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.cli import main as relight_main
from relight_torch import open_cache
from relight_torch.io.exr import read_rgb_exr
from serve_support import AUTH, bake, client

TOLERANCE = 1e-5
GREEN_GLOSS = {"inputs:diffuseColor": [0.1, 0.6, 0.2], "inputs:roughness": 0.55}


@pytest.fixture(scope="module")
def layer(tmp_path_factory):
    return bake(tmp_path_factory.mktemp("serve_materials"))


def _frame(test_client, directory) -> np.ndarray:
    """The session's converged frame, through its EXR endpoint."""
    response = test_client.get("/api/frame.exr", headers=AUTH)
    assert response.status_code == 200
    path = directory / "frame.exr"
    path.write_bytes(response.content)
    return read_rgb_exr(path)


def _wall(layer) -> str:
    relighter = open_cache(layer)
    paths = relighter.material_paths
    ids, counts = np.unique(relighter.gbuffer.material_id.numpy(), return_counts=True)
    return paths[int(ids[np.argmax(counts)])]


def test_a_material_edit_is_a_session_edit(layer, tmp_path):
    wall = _wall(layer)
    with client(layer, tmp_path) as (test_client, _):
        state = test_client.get("/api/lights", headers=AUTH).json()
        assert state["materialEdits"] and wall in state["materialPaths"] and state["materials"] == {}
        baked = _frame(test_client, tmp_path)
        response = test_client.patch(f"/api/materials{wall}", json=GREEN_GLOSS, headers=AUTH)
        assert response.status_code == 200, response.text
        edited = _frame(test_client, tmp_path)
        expected = open_cache(layer)
        expected.edit_material(wall, diffuse_color=(0.1, 0.6, 0.2), roughness=0.55)
        assert np.abs(edited - expected.render().numpy()).max() <= TOLERANCE
        assert test_client.get("/api/lights", headers=AUTH).json()["materials"] == {wall: GREEN_GLOSS}
        # Saved with the lights: `relight render --materials` renders the session's frame.
        saved = test_client.post("/api/save", json={"path": "look.usda"}, headers=AUTH)
        assert saved.status_code == 200 and "inputs:diffuseColor" in saved.json()["text"]
        out = tmp_path / "render.exr"
        assert relight_main(["render", str(layer), "--materials", str(tmp_path / "look.usda"), "-o", str(out)]) == 0
        assert np.abs(read_rgb_exr(out) - edited).max() <= TOLERANCE
        # Undo gives the baked materials back; loading the saved layer brings the edit again.
        assert test_client.post("/api/undo", headers=AUTH).status_code == 200
        assert np.abs(_frame(test_client, tmp_path) - baked).max() <= TOLERANCE
        assert test_client.post("/api/load", json={"path": "look.usda"}, headers=AUTH).status_code == 200
        assert np.abs(_frame(test_client, tmp_path) - edited).max() <= TOLERANCE


@pytest.mark.parametrize(
    ("prim", "values", "message"),
    [
        ("/World/Nope", {"inputs:roughness": 0.5}, "no material of the cache at this prim"),
        ("{wall}", {"inputs:roughnes": 0.5}, "is not a UsdPreviewSurface input"),
        ("{wall}", {"inputs:diffuseColor": [0.1, 0.2]}, "diffuse_color takes 3 numbers"),
        ("{wall}", {"inputs:opacity": 0.5}, "opacity changes the shadows"),
        ("{wall}", {}, "non-empty JSON object"),
    ],
)
def test_bad_material_edits_are_refused_and_change_nothing(layer, tmp_path, prim, values, message):
    with client(layer, tmp_path) as (test_client, session):
        version = session.version
        response = test_client.patch(f"/api/materials{prim.replace('{wall}', _wall(layer))}", json=values, headers=AUTH)
        assert response.status_code == 400 and message in response.json()["error"]
        assert session.version == version
