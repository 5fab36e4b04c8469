"""Helpers of the `relight serve` tests: a tiny baked cache and sessions over it."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

from starlette.testclient import TestClient

from cache_support import bake_bundled
from pipeline.serve.app import create_app
from pipeline.serve.session import Session

TOKEN = "test-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
SCENE = "cornell_box"


def bake(directory: Path) -> Path:
    """A 32x32 direct cache of the Cornell box under `directory`; its layer."""
    return bake_bundled(SCENE, directory)


@contextlib.contextmanager
def client(
    layer: Path, out_dir: Path, reference: Path | None = None, lights: Path | None = None
) -> Iterator[tuple[TestClient, Session]]:
    """A TestClient of a fresh session over `layer` (lifespan run: the render thread is up)."""
    session = Session.open(layer, lights_layer=lights, reference=reference, out_dir=out_dir)
    try:
        with TestClient(create_app(session, TOKEN), base_url="http://127.0.0.1:8000") as test_client:
            yield test_client, session
    finally:
        session.close()
