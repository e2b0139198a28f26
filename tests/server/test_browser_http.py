"""The browser spectator's files over plain HTTP on the server's port: content types,
caching (hashed names kept for good, the page and /avatar.json revalidated with ETags),
404 for anything else; and the bind skeleton the page is given is the desktop viewer's."""

from __future__ import annotations

import asyncio
import http
import json
import re

import numpy as np
import pytest
from conftest import serving
from test_http_metrics import TIMEOUT, fresh

from posecast.client.viewer.skinning import _bind
from posecast.server.app import Session
from posecast.server.web import NOT_BUILT, STATIC_DIR, bind_skeleton, web_routes
from posecast.server.web_mesh import compact_mesh
from posecast.solver.readers.gltf import load_makehuman, makehuman_path

Reply = tuple[int, dict[str, str], bytes]


async def request(url: str, path: str, method: str = "GET", **headers: str) -> Reply:
    """One request over a raw socket: status, headers (lower-case names), body."""
    host, port = url.removeprefix("ws://").split(":")
    reader, writer = await asyncio.open_connection(host, int(port))
    extra = "".join(f"{k.replace('_', '-')}: {v}\r\n" for k, v in headers.items())
    writer.write(f"{method} {path} HTTP/1.1\r\nHost: {host}\r\n{extra}\r\n".encode())
    raw = await asyncio.wait_for(reader.read(), TIMEOUT)  # the server closes after it
    writer.close()
    head, _, body = raw.partition(b"\r\n\r\n")
    status_line, *lines = head.decode("latin-1").split("\r\n")
    got = {k.strip().lower(): v.strip() for k, v in (ln.split(":", 1) for ln in lines)}
    assert int(got["content-length"]) == len(body)
    return int(status_line.split()[1]), got, body


@pytest.fixture(scope="module")
def rig_session() -> Session:
    return Session()


def test_the_page_its_files_and_the_mesh_are_served_with_their_types_and_caching(
        rig_session: Session) -> None:
    if not (STATIC_DIR / "index.html").exists():
        pytest.fail("server/static holds no built page: run make setup")

    async def scenario() -> None:
        async with serving(fresh(rig_session)) as url:
            status, headers, page = await request(url, "/?room=anything")
            assert status == 200 and headers["content-type"] == "text/html; charset=utf-8"
            # the page names hashed files: it is revalidated on every load
            assert headers["cache-control"] == "no-cache" and headers["etag"]
            assert "default-src 'self'" in headers["content-security-policy"]
            assert headers["x-content-type-options"] == "nosniff"
            named = re.findall(r'"(/static/[^"]+)"', page.decode())
            kinds = {".js": "text/javascript; charset=utf-8", ".css": "text/css; charset=utf-8"}
            assert len(named) == 3  # the script, its network worker and the style
            for path in named:
                status, got, body = await request(url, path)
                assert status == 200 and body, path
                assert got["content-type"] == kinds[path[path.rindex("."):]], path
                assert got["cache-control"] == "public, max-age=31536000, immutable", path
            # an unchanged page costs a 304 and no body
            status, got, body = await request(url, "/", If_None_Match=headers["etag"])
            assert (status, body, got["etag"]) == (304, b"", headers["etag"])
            status, _, _ = await request(url, "/", If_None_Match='"another"')
            assert status == 200
            status, headers, doc = await request(url, "/avatar.json")
            assert status == 200 and headers["content-type"] == "application/json"
            assert headers["cache-control"] == "no-cache"
            mesh = json.loads(doc)["mesh"]
            status, headers, body = await request(url, mesh)
            assert status == 200 and headers["content-type"] == "model/gltf-binary"
            assert headers["cache-control"].endswith("immutable")
            assert body == compact_mesh(makehuman_path().read_bytes())  # what the page draws
            status, headers, _ = await request(url, "/static/licenses.txt")
            assert status == 200 and headers["cache-control"] == "no-cache"
            # nothing else: other names, a way out of the folder, other methods
            for path in ("/static/app.js", "/static/../app.py", "/server/app.py",
                         "/index.html", "/nowhere"):
                status, _, body = await request(url, path)
                assert status == 404 and b"/healthz" in body and b"/static/" not in body, path
            status, headers, _ = await request(url, "/", method="POST")
            assert status == 405 and headers["allow"] == "GET"

    asyncio.run(scenario())


def test_an_unbuilt_page_says_how_to_build_it(tmp_path) -> None:  # type: ignore[no-untyped-def]
    reply = web_routes(tmp_path)["/"]()
    assert reply.status == http.HTTPStatus.SERVICE_UNAVAILABLE
    assert reply.body.decode() == NOT_BUILT.format(dir=tmp_path)
    assert reply.body.count(b"\n") == 1 and b"make setup" in reply.body


def test_the_bind_skeleton_is_the_desktop_viewers() -> None:
    """server.web computes it apart (the server imports nothing of client/)."""
    offsets, shift = bind_skeleton()
    bind, viewer_shift = _bind(load_makehuman().skeleton)
    np.testing.assert_array_equal(offsets, bind.offsets)
    np.testing.assert_array_equal(shift, viewer_shift)
