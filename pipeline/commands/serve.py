"""`relight serve`: edit a cache's lights live in the browser (docs/SERVE.md)."""

from __future__ import annotations

import argparse
import logging
import secrets
from pathlib import Path

from pipeline.commands.common import (
    add_device_option,
    add_lights_option,
    add_materials_option,
    add_memory_budget_option,
    relight_settings,
)
from pipeline.errors import RelightError

log = logging.getLogger("relight")


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "serve",
        help="edit a cache's lights live in the browser",
        description="Open CACHE for relighting and serve a page where its lights are edited live: "
        "sliders per UsdLux attribute, click-to-place, add and remove lights, undo, light-group and "
        "A/B views, save a layer of the changes. Prints a URL carrying the session's token; the same "
        "HTTP and WebSocket API drives the session from scripts (docs/SERVE.md).",
    )
    parser.add_argument("cache", metavar="CACHE", help="cache layer written by `relight bake`")
    add_lights_option(parser)
    add_materials_option(parser, ", for the whole session (direct and cuts caches)")
    add_device_option(parser)
    parser.add_argument("--reference", metavar="EXR", help="image to compare against (A/B view, PSNR)")
    parser.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on (default: 127.0.0.1, this machine only; another address exposes the "
        "session to the network, still behind its token)",
    )
    parser.add_argument("--port", type=int, default=0, help="port (default: 0, a free one)")
    parser.add_argument(
        "-o", "--out", default=".", metavar="DIR", help="the folder saved and loaded layers live in (default: .)"
    )
    parser.add_argument("--shadows", default="embree", choices=("embree", "shadowmaps"), help="as for `relight render`")
    add_memory_budget_option(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    # Imported here: the server's packages load only for this command (`relight --help` stays quick).
    from pipeline.serve.app import LOOPBACK_NAMES, create_app
    from pipeline.serve.server import bind, is_loopback, server
    from pipeline.serve.session import Session

    if not 0 <= args.port <= 65535:
        raise RelightError(f"--port {args.port}: must be 0..65535")
    settings = relight_settings(args)
    listener = bind(args.host, args.port)
    session = Session.open(
        args.cache, args.lights, args.reference, Path(args.out), args.device, args.shadows, settings, args.materials
    )
    token = secrets.token_urlsafe(32)
    # Bound to every interface, the page may be reached by any of the machine's names.
    everywhere = args.host in ("0.0.0.0", "::")
    app = create_app(session, token, None if everywhere else (*LOOPBACK_NAMES, args.host))
    host, port = listener.getsockname()[:2]
    shown = f"[{host}]" if ":" in host else host
    if not is_loopback(args.host):
        log.warning("serving on %s: reachable from the network (every request still needs the token)", args.host)
    print(f"relight serve: {args.cache}: http://{shown}:{port}/?token={token}", flush=True)
    try:
        server(app).run(sockets=[listener])
    finally:
        session.close()
    return 0
