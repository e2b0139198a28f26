"""Plain HTTP on the websocket port: ``GET /healthz``, ``GET /metrics`` and the browser
spectator (``/``, its files: ``server.web``).

websockets hands every opening request to ``HttpRoutes`` (its ``process_request`` hook)
before the handshake: a websocket upgrade goes on as before, on any path; any other
request is answered from the route table and the connection closed. A route is a path
and a function of no arguments; paths are looked up whole, so no request names a file
the table does not hold.
"""

from __future__ import annotations

import dataclasses
import http
import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING
from urllib.parse import urlsplit

from websockets.asyncio.server import ServerConnection
from websockets.datastructures import Headers
from websockets.http11 import Request, Response

from posecast.server.clock import now
from posecast.server.prometheus import CONTENT_TYPE, metrics_text

if TYPE_CHECKING:  # the routes read the session: imported for its type alone
    from posecast.server.app import Session


@dataclass(frozen=True)
class Reply:
    body: bytes
    content_type: str
    status: http.HTTPStatus = http.HTTPStatus.OK
    cache: str = "no-store"  # Cache-Control: by default nothing keeps it (health, metrics)
    # with it, a request whose If-None-Match names it gets 304 and no body
    etag: str | None = None
    headers: tuple[tuple[str, str], ...] = ()
    # the body gzipped ahead (the page's files): sent to a client that accepts gzip
    gzipped: bytes | None = None


Route = Callable[[], Reply]

# /metrics costs ~0.5 ms of the event loop to build (every frame waits meanwhile): made at
# most once a second, so that a client asking in a loop costs what any request costs.
# Prometheus scrapes every 15 s or so
METRICS_MAX_AGE_S = 1.0


class HttpRoutes:
    """``process_request`` for websockets' ``serve``: GET on a known path gets its
    route's reply; an unknown path 404, another method 405. A websocket upgrade goes on
    unless ``admit`` answers it with a refusal."""

    def __init__(self, routes: Mapping[str, Route],
                 admit: Callable[[ServerConnection, Request], Reply | None] | None = None
                 ) -> None:
        self.routes = dict(routes)
        self.admit = admit

    def __call__(self, connection: ServerConnection, request: Request) -> Response | None:
        if _is_upgrade(request):  # a websocket client: the handshake goes on, if admitted
            refusal = self.admit(connection, request) if self.admit is not None else None
            return None if refusal is None else _response(refusal)
        route = self.routes.get(urlsplit(request.path).path)
        if route is None:
            pages = sorted(p for p in self.routes if not p.startswith("/static/"))
            reply = _text(http.HTTPStatus.NOT_FOUND, f"no such page; try {', '.join(pages)}\n")
        elif request.method != "GET":
            reply = _text(http.HTTPStatus.METHOD_NOT_ALLOWED,
                          f"{request.method} is not allowed here: GET only\n")
        else:
            reply = route()
            if reply.gzipped is not None:  # two representations: caches must ask which
                reply = gzip_variant(reply) if accepts_gzip(request) else dataclasses.replace(
                    reply, headers=(*reply.headers, ("Vary", "Accept-Encoding")))
            if reply.etag is not None and _matches(request, reply.etag):
                return _response(reply, not_modified=True)
        return _response(reply)


def session_routes(session: Session) -> HttpRoutes:
    """The routes of ``posecast serve``."""
    from posecast.server.web import web_routes  # here: server.web builds on this module

    return HttpRoutes({
        **web_routes(),  # the browser spectator: /, /avatar.json, /static/...
        "/healthz": lambda: health(session),
        "/metrics": Reused(lambda: Reply(metrics_text(session.registry), CONTENT_TYPE),
                           METRICS_MAX_AGE_S),
    }, admit=session.admit)


class Reused:
    """A route whose reply is made again only when the last one is ``max_age_s`` old."""

    def __init__(self, route: Route, max_age_s: float,
                 clock: Callable[[], float] = now) -> None:
        self.route, self.max_age_s, self.clock = route, max_age_s, clock
        self._reply: Reply | None = None
        self._made = 0.0

    def __call__(self) -> Reply:
        t = self.clock()
        if self._reply is None or not 0 <= t - self._made < self.max_age_s:
            self._reply, self._made = self.route(), t
        return self._reply


def health(session: Session) -> Reply:
    """200 while the server serves, with what it holds (for people and probes)."""
    rooms = list(session.rooms.values())
    body = {"status": "ok", "uptime_s": round(now() - session.started, 3),
            "rooms": len(rooms), "connections": session.open_connections,
            "players": sum(a.connected for r in rooms for a in r.avatars.values()),
            "spectators": sum(len(r.spectators) for r in rooms)}
    return Reply(json.dumps(body).encode() + b"\n", "application/json")


def accepts_gzip(request: Request) -> bool:
    """Accept-Encoding allows gzip (listed, or ``*``, and not with q=0; RFC 9110 12.5.3)."""
    offered = ",".join(request.headers.get_all("Accept-Encoding")).lower()
    allowed = {}
    for item in offered.split(","):
        name, _, params = item.strip().partition(";")
        q = 1.0
        for param in params.split(";"):
            key, _, value = param.strip().partition("=")
            if key == "q":
                try:
                    q = float(value)
                except ValueError:
                    q = 0.0
        if name:
            allowed[name.strip()] = q
    q = allowed.get("gzip", allowed.get("x-gzip", allowed.get("*", 0.0)))
    return q > 0.0


def gzip_variant(reply: Reply) -> Reply:
    """The gzipped representation of ``reply``: its own body, Content-Encoding and ETag
    (a strong ETag names one representation, RFC 9110 8.8.3)."""
    assert reply.gzipped is not None
    etag = None if reply.etag is None else reply.etag[:-1] + '-gz"'
    return dataclasses.replace(reply, body=reply.gzipped, etag=etag, gzipped=None,
                               headers=(*reply.headers, ("Content-Encoding", "gzip"),
                                        ("Vary", "Accept-Encoding")))


def _is_upgrade(request: Request) -> bool:
    upgrade = ",".join(request.headers.get_all("Upgrade")).lower()
    return "websocket" in upgrade


def _text(status: http.HTTPStatus, text: str) -> Reply:
    return Reply(text.encode(), "text/plain; charset=utf-8", status)


def _matches(request: Request, etag: str) -> bool:
    """If-None-Match names ``etag`` (or is ``*``), weak or strong (RFC 9110 13.1.2)."""
    wanted = ",".join(request.headers.get_all("If-None-Match"))
    tags = {t.strip().removeprefix("W/") for t in wanted.split(",")}
    return etag in tags or "*" in tags


def _response(reply: Reply, not_modified: bool = False) -> Response:
    status = http.HTTPStatus.NOT_MODIFIED if not_modified else reply.status
    body = b"" if not_modified else reply.body
    headers = Headers([("Content-Type", reply.content_type),
                       ("Content-Length", str(len(body))),
                       ("Cache-Control", reply.cache), ("Connection", "close"),
                       ("X-Content-Type-Options", "nosniff"), *reply.headers])
    if reply.etag is not None:
        headers["ETag"] = reply.etag
    if reply.status == http.HTTPStatus.METHOD_NOT_ALLOWED:
        headers["Allow"] = "GET"
    return Response(status.value, status.phrase, headers, body)
