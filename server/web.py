"""The browser spectator's files, as routes of ``server.http_routes``.

``/`` is the page (``/?room=NAME``; the room is read by its script), ``/static/...`` its
script and style, built by ``client/web/build.mjs`` into ``server/static`` with a hash of
their content in their names; ``/avatar.json`` tells the page where the avatar mesh is and
the skeleton its flesh is bound to, and the mesh itself is ``/static/avatar-HASH.glb``.

Caching: a name that holds its content's hash never changes content, so those files may
be kept a year (``immutable``: not even revalidated on reload).

Size: every file is gzipped once, when the routes are made, and sent so to a browser
that accepts it (``Content-Encoding: gzip``, ``Vary: Accept-Encoding``); the mesh is
the viewer's with only what the page draws, in its smallest types (``server.web_mesh``).
A first load is ~0.5 MB instead of ~1.8 MB. The page and
``/avatar.json`` name them, so they are revalidated on every load (``no-cache`` with an
ETag: a 304 while unchanged), and a server upgraded to a new build is seen at once.
"""

from __future__ import annotations

import functools
import gzip
import hashlib
import http
import json
import mimetypes
import re
from pathlib import Path
from typing import Any

from posecast.server.http_routes import Reply, Route
from posecast.server.web_mesh import compact_mesh
from posecast.solver.calibration import leg_joints, raise_leg_pivots
from posecast.solver.readers.gltf import load_makehuman, makehuman_path
from posecast.solver.rig import build_rig, global_pose

STATIC_DIR = Path(__file__).resolve().parent / "static"
GZIP_LEVEL = 9  # once per process, at start: the smallest files for every load after
IMMUTABLE = "public, max-age=31536000, immutable"
HASHED = re.compile(r"-[A-Z0-9]{8}\.(js|css)$")  # esbuild's [name]-[hash]
REVALIDATE = "no-cache"
# the page loads only its own files and talks only to its own server; nothing may frame
# it. 'self' covers the websocket to the same host and port (CSP level 3)
PAGE_HEADERS = (
    ("Content-Security-Policy", "default-src 'self'; connect-src 'self'; img-src 'self' "
     "data: blob:; object-src 'none'; base-uri 'none'; frame-ancestors 'none'"),
    ("Referrer-Policy", "no-referrer"),
)
# what the desktop viewer puts between the top of a head and its name (renderer.py)
LABEL_ABOVE_HEAD_M = 0.12
TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
         ".css": "text/css; charset=utf-8", ".txt": "text/plain; charset=utf-8",
         ".json": "application/json", ".glb": "model/gltf-binary"}
NOT_BUILT = ("the browser spectator was not built into {dir}: run make setup (it needs "
             "Node.js and npm)\n")


# once a process: the files are read (and hashed, ~5 ms) when the first server starts
@functools.cache
def web_routes(static_dir: Path = STATIC_DIR) -> dict[str, Route]:
    """``/``, ``/avatar.json``, the mesh, and every built file of ``static_dir`` (read
    once: a page and the files it names always come from the same build)."""
    mesh = compact_mesh(makehuman_path().read_bytes())
    mesh_path = f"/static/avatar-{_digest(mesh)[:12]}.glb"
    routes: dict[str, Route] = {
        "/avatar.json": _revalidated(lambda: avatar_document(mesh_path),
                                     "application/json"),
        mesh_path: _file(mesh, TYPES[".glb"], IMMUTABLE),
    }
    page = static_dir / "index.html"
    if not page.is_file():
        text = NOT_BUILT.format(dir=static_dir).encode()
        routes["/"] = lambda: Reply(text, "text/plain; charset=utf-8",
                                    http.HTTPStatus.SERVICE_UNAVAILABLE)
        return routes
    routes["/"] = _file(page.read_bytes(), TYPES[".html"], REVALIDATE, PAGE_HEADERS)
    for path in sorted(static_dir.iterdir()):
        if path.is_file() and path.name != "index.html" and not path.name.startswith("."):
            kind = TYPES.get(path.suffix) or mimetypes.guess_type(path.name)[0]
            # a name with its content's hash is for good; another (the licences) is not
            cache = IMMUTABLE if HASHED.search(path.name) else REVALIDATE
            routes[f"/static/{path.name}"] = _file(path.read_bytes(),
                                                   kind or "application/octet-stream", cache)
    return routes


def avatar_document(mesh_path: str) -> bytes:
    """``/avatar.json``: the mesh's URL and its bind skeleton, in the mesh's joint order:
    what ``client/web/src/skinning.js`` fits each avatar's flesh with."""
    offsets, shift = bind_skeleton()
    sk = load_makehuman().skeleton
    head = sk.index("head")
    doc: dict[str, Any] = {
        "mesh": mesh_path, "joints": list(sk.names), "parents": [int(p) for p in sk.parents],
        "bind_offsets": offsets.tolist(), "bind_shift": shift.tolist(),
        "head_tip": sk.tips[head].tolist(), "label_above_head_m": LABEL_ABOVE_HEAD_M}
    return json.dumps(doc, separators=(",", ":")).encode()


@functools.cache
def bind_skeleton() -> tuple[Any, Any]:
    """The mesh's bind skeleton: its offsets (J, 3), with hips and knees raised where
    calibration puts every avatar's, and each joint's rest position less the bind one's.
    The desktop viewer's ``client.viewer.skinning._bind``, which the server cannot import
    (a test holds the two equal)."""
    sk = load_makehuman().skeleton
    rig = build_rig(sk)
    gq, _ = global_pose(sk, rig.canonical)
    offsets = sk.offsets.copy()
    raise_leg_pivots(sk.parents, leg_joints(rig), offsets, gq, [0.0, 1.0, 0.0])
    shift = sk.rest_positions() - sk.with_offsets(offsets).rest_positions()
    return offsets, shift


def _digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _file(body: bytes, content_type: str, cache: str,
          headers: tuple[tuple[str, str], ...] = ()) -> Route:
    reply = Reply(body, content_type, cache=cache, etag=f'"{_digest(body)[:16]}"',
                  headers=headers, gzipped=gzipped(body))
    return lambda: reply


def gzipped(body: bytes) -> bytes | None:
    """``body`` gzipped (level 9, no timestamp: the same bytes every start), or None
    where that saves under a tenth."""
    packed = gzip.compress(body, GZIP_LEVEL, mtime=0)
    return packed if len(packed) < 0.9 * len(body) else None


def _revalidated(make: Any, content_type: str) -> Route:
    """A reply made once, when first asked for, and revalidated by browsers."""
    @functools.cache
    def route() -> Reply:
        body = make()
        return Reply(body, content_type, cache=REVALIDATE, etag=f'"{_digest(body)[:16]}"',
                     gzipped=gzipped(body))
    return route
