"""What the browser page costs to load: its files gzipped where the browser accepts it,
and the avatar mesh compacted to what the page draws (issue 30, item 4)."""

from __future__ import annotations

import asyncio
import gzip
import json
import re

import numpy as np
import pytest
from conftest import serving
from test_browser_http import request
from test_http_metrics import fresh

from posecast.server.app import Session
from posecast.server.web import STATIC_DIR
from posecast.server.web_mesh import (
    QUANTIZATION,
    MeshFormatError,
    accessor_array,
    byte_weights,
    compact_mesh,
    read_glb,
)
from posecast.solver.readers.gltf import makehuman_path

GZIP = {"Accept_Encoding": "gzip, deflate, br"}


def _attributes(glb: bytes) -> tuple[dict[str, np.ndarray], np.ndarray]:
    doc, binary = read_glb(glb)
    prim = doc["meshes"][0]["primitives"][0]
    return ({k: accessor_array(doc, binary, i) for k, i in prim["attributes"].items()},
            accessor_array(doc, binary, prim["indices"]))


def test_the_compact_mesh_holds_what_the_page_draws() -> None:
    full = makehuman_path().read_bytes()
    small = compact_mesh(full)
    assert len(small) < 0.5 * len(full)
    before, triangles = _attributes(full)
    after, triangles_after = _attributes(small)
    assert sorted(after) == ["JOINTS_0", "NORMAL", "POSITION", "WEIGHTS_0"]  # no UVs
    np.testing.assert_array_equal(after["POSITION"], before["POSITION"])
    np.testing.assert_array_equal(after["JOINTS_0"], before["JOINTS_0"])
    assert after["JOINTS_0"].dtype == np.uint8 and triangles_after.dtype == np.uint16
    np.testing.assert_array_equal(triangles_after, triangles)
    # weights: bytes summing to exactly 255, each within a byte's rounding and a unit
    w = after["WEIGHTS_0"].astype(np.int64)
    assert (w.sum(axis=1) == 255).all()
    want = before["WEIGHTS_0"] / before["WEIGHTS_0"].sum(axis=1, keepdims=True)
    assert np.abs(w / 255 - want).max() <= 1.0 / 255
    # normals: signed bytes (KHR_mesh_quantization), within half a degree
    n0 = before["NORMAL"] / np.linalg.norm(before["NORMAL"], axis=1, keepdims=True)
    n1 = after["NORMAL"].astype(np.float64)
    n1 /= np.linalg.norm(n1, axis=1, keepdims=True)
    assert np.degrees(np.arccos(np.clip((n0 * n1).sum(axis=1), -1.0, 1.0))).max() < 0.5
    doc, _ = read_glb(small)
    assert QUANTIZATION in doc["extensionsRequired"]
    for view in doc["bufferViews"]:  # glTF: every view 4-byte aligned, strides too
        assert view["byteOffset"] % 4 == 0 and view.get("byteStride", 4) % 4 == 0
    # the skin is the same
    assert json.dumps(doc["skins"]) and len(doc["nodes"]) == len(read_glb(full)[0]["nodes"])


def test_byte_weights_sum_to_255_and_stay_nearest() -> None:
    rng = np.random.default_rng(1)
    w = rng.dirichlet([0.3, 0.3, 0.3, 0.3], size=20000)
    w[:100, 1:] = 0.0  # a joint alone (its row sums to less than one: normalised)
    b = byte_weights(w)
    assert (b.astype(np.int64).sum(axis=1) == 255).all()
    assert np.abs(b / 255 - w / w.sum(axis=1, keepdims=True)).max() < 1.0 / 255
    assert (b[:100, 0] == 255).all()


def test_a_file_that_is_no_mesh_is_one_clear_error() -> None:
    with pytest.raises(MeshFormatError, match="not a binary glTF"):
        compact_mesh(b"PK\x03\x04 a zip")


def test_the_first_load_is_a_third_of_the_uncompressed_one() -> None:
    """The page and every file it loads, gzipped, against the same files as they were
    served before (identity, the full mesh): at most a third of the bytes."""
    if not (STATIC_DIR / "index.html").exists():
        pytest.fail("server/static holds no built page: run make setup")

    async def scenario() -> tuple[int, int]:
        async with serving(fresh(Session())) as url:
            sent = before = 0
            status, headers, page = await request(url, "/?room=r", **GZIP)
            assert status == 200 and headers["content-encoding"] == "gzip"
            html = gzip.decompress(page)
            sent, before = sent + len(page), before + len(html)
            paths = re.findall(r'"(/static/[^"]+)"', html.decode())
            assert len(paths) == 3
            for path in [*paths, "/avatar.json"]:
                status, headers, body = await request(url, path, **GZIP)
                assert status == 200 and headers["vary"] == "Accept-Encoding", path
                plain = gzip.decompress(body) if headers.get("content-encoding") else body
                sent, before = sent + len(body), before + len(plain)
                if path == "/avatar.json":
                    mesh = json.loads(plain)["mesh"]
            status, headers, body = await request(url, mesh, **GZIP)
            assert status == 200 and headers["content-encoding"] == "gzip"
            assert gzip.decompress(body) == compact_mesh(makehuman_path().read_bytes())
            sent += len(body)
            before += len(makehuman_path().read_bytes())  # what the page loaded before
            return sent, before

    sent, before = asyncio.run(scenario())
    print(f"first load: {sent} bytes, before {before} ({sent / before:.1%})")
    assert sent <= before / 3


def test_gzip_only_where_accepted_with_its_own_etag() -> None:
    async def scenario() -> None:
        async with serving(fresh(Session())) as url:
            status, plain_headers, plain = await request(url, "/avatar.json")
            assert status == 200 and "content-encoding" not in plain_headers
            assert plain_headers["vary"] == "Accept-Encoding"
            for accept, packed in (("gzip", True), ("gzip;q=0, identity", False),
                                   ("br", False), ("*", True), ("GZIP;q=0.5", True),
                                   ("gzip;q=x", False)):
                status, headers, body = await request(url, "/avatar.json",
                                                      Accept_Encoding=accept)
                assert status == 200, accept
                assert (headers.get("content-encoding") == "gzip") is packed, accept
                assert (gzip.decompress(body) if packed else body) == plain, accept
                assert (headers["etag"] != plain_headers["etag"]) is packed, accept
            # each representation revalidates against its own ETag
            _, headers, _ = await request(url, "/avatar.json", **GZIP)
            status, _, body = await request(url, "/avatar.json", **GZIP,
                                            If_None_Match=headers["etag"])
            assert (status, body) == (304, b"")
            status, _, _ = await request(url, "/avatar.json",
                                         If_None_Match=headers["etag"])
            assert status == 200  # the plain one has another tag

    asyncio.run(scenario())
