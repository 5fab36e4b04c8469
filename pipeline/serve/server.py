"""Running the session's application under uvicorn: on a socket bound first (so the printed URL
names the real port when --port is 0), in the foreground (`relight serve`) or on a thread (tests,
the latency benchmark)."""

from __future__ import annotations

import contextlib
import ipaddress
import socket
import threading
import time
from collections.abc import Iterator

import uvicorn

from pipeline.errors import RelightError


def bind(host: str, port: int) -> socket.socket:
    """A listening socket on host:port (port 0: a free one).

    Raises:
        RelightError: the host does not resolve or the address cannot be listened on.
    """
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as error:
        raise RelightError(f"--host {host}: {error.strerror}") from None
    family, kind, proto, _, address = infos[0]
    listener = socket.socket(family, kind, proto)
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        listener.bind(address)
    except OSError as error:
        listener.close()
        raise RelightError(f"--host {host} --port {port}: cannot listen there: {error.strerror}") from None
    listener.listen(64)
    return listener


def is_loopback(host: str) -> bool:
    """Whether `host` names this machine only (localhost or a loopback address)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def server(app: object) -> uvicorn.Server:
    """A uvicorn server of `app` (its WebSocket protocol from the websockets package, sans-I/O implementation)."""
    return uvicorn.Server(uvicorn.Config(app, log_level="warning", ws="websockets-sansio"))  # type: ignore[arg-type]


@contextlib.contextmanager
def serving(app: object, host: str = "127.0.0.1", timeout: float = 30.0) -> Iterator[str]:
    """Serve `app` on a thread, on a free port of `host`; yields its base URL ('http://host:port').

    Raises:
        RuntimeError: the server did not start within `timeout` seconds.
    """
    listener = bind(host, 0)
    running = server(app)
    thread = threading.Thread(target=running.run, kwargs={"sockets": [listener]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + timeout
    while not running.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            raise RuntimeError("the uvicorn server did not start")
        time.sleep(0.01)
    try:
        port = listener.getsockname()[1]
        yield f"http://{host}:{port}"
    finally:
        running.should_exit = True
        thread.join(timeout)
        listener.close()
