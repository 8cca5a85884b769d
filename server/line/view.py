"""The line view's own small web server: the page, its scripts, and where the broker is.

The line view (clients/hmi/line.html) reads every cell from the plant's MQTT broker
over the broker's WebSocket listener, not from any one cell: a cell's own pages may
talk only to their own origin (server/api/dashboard.py), and a line view must keep
showing the other cells, and this one as offline, when a cell is down. So it is
served apart, by this module, with a Content-Security-Policy that lets the page
connect to its own origin and to that one broker, and nothing else.

    python -m server.line.view --port 8080 --broker-ws ws://127.0.0.1:9001

`GET /` is the page, `/hmi/...` its files (the same open files a cell serves),
`GET /line-config.json` the broker's WebSocket URL and the topic prefix.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path
from urllib.parse import urlsplit

import uvicorn
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles

from server.api.dashboard import HMI_DIR, SECURITY_HEADERS

PAGE = "line.html"
DEFAULT_PREFIX = "glue"


def security_headers(broker_ws: str) -> dict[str, str]:
    """The dashboard's headers, with the broker's WebSocket origin allowed to connect."""
    csp = SECURITY_HEADERS["Content-Security-Policy"].replace(
        "connect-src 'self'", f"connect-src 'self' {broker_ws}"
    )
    return {**SECURITY_HEADERS, "Content-Security-Policy": csp}


def websocket_origin(url: str) -> str:
    """`ws://host:port` of a broker URL (path dropped); ValueError if it is not ws(s)."""
    parts = urlsplit(url)
    if parts.scheme not in ("ws", "wss") or not parts.hostname:
        raise ValueError(f"not a WebSocket URL: {url!r} (expected ws://host:port)")
    return f"{parts.scheme}://{parts.netloc}"


class _Assets(StaticFiles):
    def __init__(self, headers: dict[str, str], directory: Path) -> None:
        super().__init__(directory=directory)
        self._headers = headers

    def file_response(self, *args: object, **kwargs: object) -> Response:
        response = super().file_response(*args, **kwargs)  # type: ignore[arg-type]
        response.headers.update(self._headers)
        return response


def create_line_view(
    broker_ws: str, prefix: str = DEFAULT_PREFIX, directory: Path = HMI_DIR
) -> Starlette:
    """The line view's app for the broker at `broker_ws` (what the browser connects to)."""
    origin = websocket_origin(broker_ws)
    headers = security_headers(origin)
    page = directory / PAGE
    if not page.is_file():
        raise FileNotFoundError(f"the line view's page is missing: {page}")

    async def line_page(_: Request) -> Response:
        return FileResponse(page, media_type="text/html", headers=headers)

    async def line_config(_: Request) -> Response:
        return JSONResponse({"broker": broker_ws, "prefix": prefix}, headers=headers)

    return Starlette(
        routes=[
            Route("/", line_page),
            Route("/line-config.json", line_config),
            Mount("/hmi", _Assets(headers, directory)),
        ]
    )


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m server.line.view", description="Serve the line view of a line of cells."
    )
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=8080, help="HTTP port (default 8080)")
    parser.add_argument(
        "--broker-ws",
        required=True,
        help="the broker's WebSocket listener as the browser reaches it, e.g. ws://host:9001",
    )
    parser.add_argument("--prefix", default=DEFAULT_PREFIX, help="the cells' topic prefix")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> None:
    args = parse_args(argv)
    app = create_line_view(args.broker_ws, args.prefix)
    print(f"line view on http://{args.host}:{args.port}/ (broker {args.broker_ws})", flush=True)
    uvicorn.run(app, host=args.host, port=args.port, log_level="warning")


if __name__ == "__main__":
    main()
