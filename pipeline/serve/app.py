"""The HTTP and WebSocket API of a session (docs/SERVE.md), as a Starlette application.

Every request needs the session token (`Authorization: Bearer TOKEN` or `?token=TOKEN`); a
WebSocket upgrade whose `Origin` is not this server's own address is refused (a page on another
site cannot drive the session through the browser). A bad request is a 4xx with a JSON body
`{"error": "<one line>"}` and the session goes on; the page uses this same API.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import json
import logging
from collections.abc import AsyncIterator
from importlib import resources
from typing import Any
from urllib.parse import parse_qs, urlsplit

from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException
from starlette.requests import Request
from starlette.responses import HTMLResponse, JSONResponse, Response
from starlette.routing import Route, WebSocketRoute
from starlette.types import ASGIApp, Receive, Scope, Send
from starlette.websockets import WebSocket, WebSocketDisconnect

from pipeline.errors import RelightError
from pipeline.serve.attributes import attribute_checks
from pipeline.serve.display import Display, exr_bytes, frame_psnr, png_bytes, view_image
from pipeline.serve.rig import UnknownLight
from pipeline.serve.session import Frame, Session
from pipeline.serve.stream import FrameStream
from relight_torch.lights.light import LightKind

log = logging.getLogger("relight")

MAX_BODY_BYTES = 16 * 2**20
"""Largest request body (a lights layer's text is the biggest thing a client sends)."""
LOOPBACK_NAMES = ("127.0.0.1", "localhost", "::1", "[::1]")


class BadRequest(Exception):
    """A client error with its HTTP status."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status


def create_app(session: Session, token: str, hosts: tuple[str, ...] | None = LOOPBACK_NAMES) -> ASGIApp:
    """The application serving `session`: its Starlette routes behind the token and Origin guard.

    Args:
        token: the secret every request must carry.
        hosts: host names the page may be loaded from (the bound host and the loopback names): a
            WebSocket's Origin must name one of them, and be the address the request came in on
            (its Host). None (a server bound to every interface): any name, same origin only.
    """
    stream = FrameStream(session)

    @contextlib.asynccontextmanager
    async def lifespan(app: Starlette) -> AsyncIterator[None]:
        stream.start()
        try:
            yield
        finally:
            await run_in_threadpool(stream.stop)

    async def page(request: Request) -> Response:
        text = resources.files("pipeline.serve").joinpath("page.html").read_text(encoding="utf-8")
        return HTMLResponse(text, headers={"Cache-Control": "no-store", "Referrer-Policy": "no-referrer"})

    async def info(request: Request) -> Response:
        description = session.description
        return JSONResponse(
            {
                "cache": description.layer,
                "method": description.method,
                "width": session.width,
                "height": session.height,
                "reference": session.reference is not None,
                "outDir": str(session.files.out_dir),
                "types": [kind.value for kind in LightKind],
                "attributes": {kind.value: attribute_checks(kind) for kind in LightKind},
            }
        )

    async def lights(request: Request) -> Response:
        return JSONResponse(await run_in_threadpool(session.state))

    async def add_light(request: Request) -> Response:
        body = await _json_object(request)
        kind, path, values = body.get("type"), body.get("path"), body.get("attributes")
        if values is not None and not isinstance(values, dict):
            raise RelightError("attributes must be a JSON object of attribute values")
        new_path = await run_in_threadpool(session.add, kind, path, values)
        return JSONResponse({"path": new_path, "version": session.version}, status_code=201)

    async def edit_light(request: Request) -> Response:
        body = await _json_object(request)
        gesture = request.query_params.get("gesture")
        version = await run_in_threadpool(session.edit, _prim(request), body, gesture)
        return JSONResponse({"version": version})

    async def edit_material(request: Request) -> Response:
        body = await _json_object(request)
        gesture = request.query_params.get("gesture")
        version = await run_in_threadpool(session.edit_material, _prim(request), body, gesture)
        return JSONResponse({"version": version})

    async def remove_light(request: Request) -> Response:
        version = await run_in_threadpool(session.remove, _prim(request))
        return JSONResponse({"version": version})

    async def place(request: Request) -> Response:
        body = await _json_object(request)
        path = body.get("path")
        if not isinstance(path, str):
            raise RelightError("place: 'path' must be a light's prim path")
        version = await run_in_threadpool(
            session.place, path, body.get("x"), body.get("y"), body.get("mode", "aim"), body.get("distance")
        )
        return JSONResponse({"version": version})

    async def undo(request: Request) -> Response:
        return JSONResponse({"version": await run_in_threadpool(session.undo)})

    async def redo(request: Request) -> Response:
        return JSONResponse({"version": await run_in_threadpool(session.redo)})

    async def save(request: Request) -> Response:
        body = await _json_object(request, allow_empty=True)
        path = body.get("path")
        written = None if path is None else await run_in_threadpool(session.save, path)
        text = await run_in_threadpool(session.save_text)
        return JSONResponse({"text": text, "path": None if written is None else str(written)})

    async def load(request: Request) -> Response:
        body = await _json_object(request)
        version = await run_in_threadpool(session.load, body.get("path"), body.get("text"))
        return JSONResponse({"version": version})

    async def frame_png(request: Request) -> Response:
        display = Display.parse(request.query_params.get("view", "beauty"), request.query_params.get("exposure", "0"))
        frame = await _frame(display)
        image = view_image(frame, display, session.reference)
        data = await run_in_threadpool(png_bytes, image, display.exposure)
        return Response(data, media_type="image/png", headers=_frame_headers(frame))

    async def frame_exr(request: Request) -> Response:
        display = Display.parse(request.query_params.get("view", "beauty"))
        frame = await _frame(display)
        data = await run_in_threadpool(exr_bytes, view_image(frame, display, session.reference))
        return Response(data, media_type="image/x-exr", headers=_frame_headers(frame))

    async def _frame(display: Display) -> Frame:
        try:
            frame = await run_in_threadpool(stream.wait_frame)
            if display.group is not None and frame.groups is None:
                frame = await run_in_threadpool(_frame_with_groups)
        except RuntimeError as error:
            raise BadRequest(503, str(error)) from None
        return frame

    def _frame_with_groups() -> Frame:
        frames = list(session.frames(groups=True))
        return frames[-1]

    def _frame_headers(frame: Frame) -> dict[str, str]:
        return {"X-Relight-Version": str(frame.version), "Cache-Control": "no-store"}

    async def frames_socket(websocket: WebSocket) -> None:
        await websocket.accept()
        viewer = _Viewer(asyncio.get_running_loop())
        unsubscribe = stream.subscribe(viewer)
        sender = asyncio.create_task(_send_frames(websocket, viewer, session))
        try:
            while True:
                message = await websocket.receive()
                if message["type"] == "websocket.disconnect":
                    break
                try:
                    if message.get("text") is None:
                        raise RelightError("messages are JSON text")
                    settings = json.loads(message["text"])
                    if not isinstance(settings, dict) or settings.get("type") != "display":
                        raise RelightError('a message is {"type": "display", "view": ..., "exposure": ...}')
                    viewer.set_display(Display.parse(settings.get("view", "beauty"), settings.get("exposure", 0.0)))
                    stream.poke()
                except (ValueError, RecursionError, RelightError) as error:
                    await websocket.send_json({"type": "error", "error": str(error).splitlines()[0]})
        except WebSocketDisconnect:
            pass
        finally:
            unsubscribe()
            sender.cancel()

    routes = [
        Route("/", page),
        Route("/api/session", info),
        Route("/api/lights", lights, methods=["GET"]),
        Route("/api/lights", add_light, methods=["POST"]),
        Route("/api/lights/{prim:path}", edit_light, methods=["PATCH"]),
        Route("/api/lights/{prim:path}", remove_light, methods=["DELETE"]),
        Route("/api/materials/{prim:path}", edit_material, methods=["PATCH"]),
        Route("/api/place", place, methods=["POST"]),
        Route("/api/undo", undo, methods=["POST"]),
        Route("/api/redo", redo, methods=["POST"]),
        Route("/api/save", save, methods=["POST"]),
        Route("/api/load", load, methods=["POST"]),
        Route("/api/frame.png", frame_png),
        Route("/api/frame.exr", frame_exr),
        WebSocketRoute("/api/frames", frames_socket),
    ]
    handlers = {
        RelightError: _error(400),
        UnknownLight: _error(404),
        BadRequest: lambda request, error: _json_error(error.status, str(error)),
        HTTPException: lambda request, error: _json_error(error.status_code, str(error.detail)),
        Exception: _internal_error,
    }
    app = Starlette(routes=routes, exception_handlers=handlers, lifespan=lifespan)  # type: ignore[arg-type]
    return _Guard(app, token, hosts)


class _Viewer:
    """One WebSocket client: its display settings and the newest frame for it (older ones dropped)."""

    def __init__(self, loop: asyncio.AbstractEventLoop):
        self.display = Display()
        self.frame: Frame | None = None
        self.failure: tuple[int, str] | None = None
        self.ready = asyncio.Event()
        self._loop = loop

    def wants_groups(self) -> bool:
        return self.display.group is not None

    def set_display(self, display: Display) -> None:
        self.display = display
        self.ready.set()  # re-send the newest frame through the new settings

    def deliver(self, frame: Frame) -> None:
        self.frame = frame
        self._loop.call_soon_threadsafe(self.ready.set)

    def failed(self, version: int, message: str) -> None:
        self.failure = (version, message)
        self._loop.call_soon_threadsafe(self.ready.set)


async def _send_frames(websocket: WebSocket, viewer: _Viewer, session: Session) -> None:
    """Send the viewer's newest frame each time one arrives: a JSON header, then the PNG bytes."""
    try:
        while True:
            await viewer.ready.wait()
            viewer.ready.clear()
            if viewer.failure is not None:
                version, message = viewer.failure
                viewer.failure = None
                await websocket.send_json({"type": "error", "version": version, "error": message})
            frame, display = viewer.frame, viewer.display
            if frame is None:
                continue
            try:
                image = view_image(frame, display, session.reference)
            except RelightError as error:
                if display.group is not None and frame.groups is None:
                    continue  # the render thread is making a frame with the groups
                await websocket.send_json({"type": "error", "version": frame.version, "error": str(error)})
                continue
            data = await run_in_threadpool(png_bytes, image, display.exposure)
            header = {
                "type": "frame",
                "version": frame.version,
                "final": frame.final,
                "view": display.view,
                "exposure": display.exposure,
                "psnr": frame_psnr(frame, session.reference),
            }
            await websocket.send_json(header)
            await websocket.send_bytes(data)
    except (WebSocketDisconnect, RuntimeError):
        return  # the client went away while a frame was on its way


class _Guard:
    """ASGI middleware: the token on every request, and a WebSocket Origin check."""

    def __init__(self, app: ASGIApp, token: str, hosts: tuple[str, ...] | None):
        self.app = app
        self.token = token
        self.hosts = None if hosts is None else {host.lower() for host in hosts}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        headers = {key.decode("latin-1").lower(): value.decode("latin-1") for key, value in scope["headers"]}
        problem = self._problem(scope, headers)
        if problem is None:
            await self.app(scope, receive, send)
            return
        status, message = problem
        if scope["type"] == "websocket":
            await send({"type": "websocket.close", "code": 4000 + status, "reason": message})
            return
        await _json_error(status, message)(scope, receive, send)

    def _problem(self, scope: Scope, headers: dict[str, str]) -> tuple[int, str] | None:
        query = parse_qs(scope.get("query_string", b"").decode("latin-1"))
        given = headers.get("authorization", "")
        token = given[len("Bearer ") :] if given.startswith("Bearer ") else (query.get("token") or [""])[0]
        if not hmac.compare_digest(token.encode("utf-8", "replace"), self.token.encode("utf-8")):
            return 401, "missing or wrong session token (Authorization: Bearer TOKEN, or ?token=TOKEN)"
        if scope["type"] == "websocket" and "origin" in headers:
            origin = urlsplit(headers["origin"])
            host = headers.get("host", "")
            known = self.hosts is None or (origin.hostname or "").lower() in self.hosts
            if origin.scheme not in ("http", "https") or origin.netloc.lower() != host.lower() or not known:
                return 403, f"WebSocket from a foreign origin {headers['origin']!r:.80} refused"
        return None


async def _json_object(request: Request, allow_empty: bool = False) -> dict[str, Any]:
    """The request's JSON object body.

    Raises:
        BadRequest: 413 for a body over MAX_BODY_BYTES; 400 for one that is not a JSON object.
    """
    declared = request.headers.get("content-length")
    if declared is not None and (not declared.isdigit() or int(declared) > MAX_BODY_BYTES):
        raise BadRequest(413, f"request body over {MAX_BODY_BYTES} bytes")
    body = b""
    async for chunk in request.stream():
        body += chunk
        if len(body) > MAX_BODY_BYTES:
            raise BadRequest(413, f"request body over {MAX_BODY_BYTES} bytes")
    if allow_empty and not body.strip():
        return {}
    try:
        value = json.loads(body)
    except (ValueError, RecursionError) as error:
        raise BadRequest(400, f"the body is not JSON: {str(error).splitlines()[0]:.120}") from None
    if not isinstance(value, dict):
        raise BadRequest(400, f"the body must be a JSON object, got {type(value).__name__}")
    return value


def _prim(request: Request) -> str:
    return "/" + request.path_params["prim"].lstrip("/")


def _error(status: int):  # type: ignore[no-untyped-def]
    def handler(request: Request, error: Exception) -> Response:
        return _json_error(status, str(error).splitlines()[0] if str(error) else type(error).__name__)

    return handler


def _json_error(status: int, message: str) -> JSONResponse:
    return JSONResponse({"error": message}, status_code=status)


def _internal_error(request: Request, error: Exception) -> Response:
    log.error("internal error serving %s %s", request.method, request.url.path, exc_info=error)
    return _json_error(
        500, f"internal error: {type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}"
    )
