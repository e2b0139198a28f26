"""Plain HTTP on the server's websocket port: /healthz, /metrics (Prometheus), 404, 405;
over real sockets on 127.0.0.1, with players and a spectator streaming."""

from __future__ import annotations

import asyncio
import json
import urllib.error
import urllib.request
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

import numpy as np
import pytest
from conftest import serving
from prometheus_client.parser import text_string_to_metric_families
from stream_decode import decode
from websockets.asyncio.client import ClientConnection, connect

from posecast.protocol import (
    PROTOCOL_VERSION,
    AvatarBatch,
    AvatarRoster,
    Calibrate,
    Error,
    ErrorCode,
    Hello,
    TrackerFrame,
    Welcome,
    encode,
)
from posecast.server.app import Session
from posecast.server.clock import now
from posecast.server.http_routes import Reply, Reused
from posecast.server.latency import (
    BUCKET_BOUNDS_S,
    SERVER_PENDING,
    SERVER_STAGES,
    ServerLatency,
    StageHistograms,
)
from posecast.solver.motion import ViveRecording
from posecast.solver.readers.vive import read_vive

TIMEOUT = 10.0  # seconds for any one reply: generous, the machine may be loaded

Samples = dict[tuple[str, tuple[tuple[str, str], ...]], float]


@pytest.fixture(scope="module")
def walk(walk_vive: Path) -> ViveRecording:
    return read_vive(walk_vive)  # frame 0: a T-pose


@pytest.fixture(scope="module")
def rig_session() -> Session:
    return Session()  # its rig, built once, is shared by each test's own Session


def fresh(rig_session: Session) -> Session:
    """A session whose counters are this test's alone; a player's avatar goes as it
    leaves (no reconnect grace), so that nothing moves once the players are gone."""
    return Session(rig_session.rig, reconnect_grace=0.0)


def poses(rec: ViveRecording, frame: int) -> np.ndarray:
    return np.concatenate([rec.positions[frame], rec.rotations[frame]], axis=1)


@asynccontextmanager
async def joined(url: str, role: str, room: str, name: str
                 ) -> AsyncIterator[ClientConnection]:
    async with connect(url, compression=None) as ws:
        await ws.send(encode(Hello(protocol_version=PROTOCOL_VERSION, role=role, room=room,
                                   display_name=name)))
        assert isinstance(decode(await asyncio.wait_for(ws.recv(), TIMEOUT)), Welcome)
        yield ws


async def next_of(ws: ClientConnection, kind: type) -> object:
    while True:
        msg = decode(await asyncio.wait_for(ws.recv(), TIMEOUT))
        if isinstance(msg, kind):
            return msg


async def http_get(url: str, path: str, method: str = "GET"
                   ) -> tuple[int, dict[str, str], bytes]:
    """One request over a raw socket: status, headers (lower-case names), body."""
    host, port = url.removeprefix("ws://").split(":")
    reader, writer = await asyncio.open_connection(host, int(port))
    writer.write(f"{method} {path} HTTP/1.1\r\nHost: {host}\r\n\r\n".encode())
    raw = await asyncio.wait_for(reader.read(), TIMEOUT)  # the server closes after it
    writer.close()
    head, _, body = raw.partition(b"\r\n\r\n")
    status_line, *lines = head.decode("latin-1").split("\r\n")
    headers = {k.strip().lower(): v.strip() for k, v in (ln.split(":", 1) for ln in lines)}
    assert int(headers["content-length"]) == len(body)
    return int(status_line.split()[1]), headers, body


def samples(text: str) -> Samples:
    """Every sample of a scrape, parsed by prometheus_client's own parser."""
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for family in text_string_to_metric_families(text) for s in family.samples}


def histogram(scraped: Samples, stage: str) -> tuple[list[tuple[float, float]], float, float]:
    """One stage's cumulative buckets (le, count), its count and its sum."""
    buckets = sorted((float(dict(labels)["le"]), v) for (name, labels), v in scraped.items()
                     if name == "posecast_latency_seconds_bucket"
                     and dict(labels)["stage"] == stage)
    key = (("stage", stage),)
    return (buckets, scraped[("posecast_latency_seconds_count", key)],
            scraped[("posecast_latency_seconds_sum", key)])


async def stream(ws: ClientConnection, rec: ViveRecording, frames: int) -> None:
    """A player: a T-pose, then ``frames`` tracker frames at 90 Hz, captured now."""
    await ws.send(encode(Calibrate(roles=rec.devices, poses=poses(rec, 0), t_capture=0.0,
                                   clock_offset=0.0)))
    for seq in range(1, frames + 1):
        await ws.send(encode(TrackerFrame(seq=seq, roles=rec.devices,
                                          poses=poses(rec, 1 + seq % (rec.num_frames - 1)),
                                          t_capture=now(), clock_offset=0.0)))
        await asyncio.sleep(1 / 90)


def test_metrics_match_the_session_counters(rig_session: Session,
                                            walk: ViveRecording) -> None:
    """Two players stream a second each to a spectator, then leave; /metrics then shows
    exactly the session's counters, and every solved avatar-frame in each histogram."""
    session, frames = fresh(rig_session), 90
    received = 0  # avatar-frames the spectator got

    async def spectate(ws: ClientConnection) -> None:
        nonlocal received
        async for data in ws:
            msg = decode(data)
            if isinstance(msg, AvatarBatch):
                received += len(msg.avatar_ids)

    async def main() -> None:
        await asyncio.wait_for(scenario(), 120)

    async def scenario() -> None:
        async with serving(session) as url, joined(url, "spectator", "m", "watcher") as spec:
            reader = asyncio.create_task(spectate(spec))
            async with joined(url, "player", "m", "one") as one, \
                    joined(url, "player", "m", "two") as two:
                # a frame before the T-pose: refused, counted by its code
                await one.send(encode(TrackerFrame(seq=0, roles=walk.devices,
                                                   poses=poses(walk, 1), t_capture=now(),
                                                   clock_offset=0.0)))
                assert isinstance(await next_of(one, Error), Error)
                status, headers, body = await http_get(url, "/healthz")  # while streaming
                await asyncio.gather(stream(one, walk, frames), stream(two, walk, frames))
            # the players left and their avatars went; nothing is left to solve or send
            while session.rooms["m"].avatars:
                await asyncio.sleep(0.01)
            assert await session.drain(TIMEOUT)
            m = session.metrics
            while received < m.frames_delivered:  # in flight to the spectator still
                await asyncio.sleep(0.01)
            before = json.dumps(m.as_json(), sort_keys=True)
            counts = {stage: m.latency.count(stage) for stage in SERVER_STAGES}
            _, metrics_headers, text = await http_get(url, "/metrics")
            assert json.dumps(m.as_json(), sort_keys=True) == before  # read at one moment
            reader.cancel()
            check_health(status, headers, body)
            check_metrics(session, metrics_headers, text.decode(), counts, frames, received)

    asyncio.run(main())


def check_health(status: int, headers: dict[str, str], body: bytes) -> None:
    assert status == 200 and headers["content-type"] == "application/json"
    health = json.loads(body)
    assert health["status"] == "ok" and health["uptime_s"] > 0
    # two players (one of them refused a frame, connected still) and a spectator
    assert (health["rooms"], health["connections"]) == (1, 3)
    assert (health["players"], health["spectators"]) == (2, 1)


def check_metrics(session: Session, headers: dict[str, str], text: str,
                  counts: dict[str, int], frames: int, received: int) -> None:
    m = session.metrics
    assert headers["content-type"].startswith("text/plain; version=0.0.4")
    scraped = samples(text)

    def value(name: str, **labels: str) -> float:
        return scraped[(name, tuple(sorted(labels.items())))]

    # the players' own numbers: every frame they sent was received; one was refused
    assert m.frames_received == 2 * frames + 1 and m.frames_rejected == 1
    assert value("posecast_frames_received_total") == 2 * frames + 1
    assert value("posecast_connections_total") == m.connections == 3  # no HTTP request
    for name in ("frames_received", "frames_solved", "frames_superseded",
                 "frames_discarded", "frames_rejected", "frames_unsendable",
                 "frames_delivered", "frames_dropped", "batches"):
        assert value(f"posecast_{name}_total") == getattr(m, name), name
    assert m.frames_solved > 0 and m.frames_delivered == received
    for code in ErrorCode:
        assert value("posecast_rejections_total", code=code.value) == m.rejected[code], code
    assert value("posecast_rejections_total", code="not_calibrated") == 1
    for limit, n in m.limited.items():
        assert value("posecast_limited_total", limit=limit) == n
    # now: the spectator alone, in the one room
    assert value("posecast_open_connections") == session.open_connections == 1
    assert (value("posecast_rooms"), value("posecast_players"),
            value("posecast_spectators")) == (1, 0, 1)
    assert value("process_resident_memory_bytes") > 0

    # one value per solved avatar-frame in each stage
    assert counts == dict.fromkeys(SERVER_STAGES, m.frames_solved)
    for stage in SERVER_STAGES:
        buckets, count, total = histogram(scraped, stage)
        assert [le for le, _ in buckets] == [*BUCKET_BOUNDS_S, float("inf")]
        assert count == buckets[-1][1] == m.frames_solved, stage
        cumulative = [c for _, c in buckets]
        assert cumulative == sorted(cumulative), stage
        # loopback: a second is far more than any stage of any frame takes
        assert 0 < total / count < 1.0 and buckets[-2][1] == count, stage
    # each frame is solved after it arrived and sent after it was solved: below any
    # bound, at least as many frames were solved as were sent
    solve, _, solve_sum = histogram(scraped, "solve")
    server, _, server_sum = histogram(scraped, "server")
    assert all(s >= v for (_, s), (_, v) in zip(solve, server, strict=True))
    assert 0 < solve_sum <= server_sum


def test_unknown_paths_and_other_methods_and_websockets_on_the_same_port(
        rig_session: Session) -> None:
    session = fresh(rig_session)

    async def main() -> None:
        async with serving(session) as url:
            status, _, body = await http_get(url, "/nowhere")
            assert status == 404 and b"/healthz" in body  # names the pages there are
            status, headers, _ = await http_get(url, "/metrics", method="POST")
            assert status == 405 and headers["allow"] == "GET"
            status, _, _ = await http_get(url, "/healthz", method="DELETE")
            assert status == 405
            status, _, body = await http_get(url, "/healthz?verbose=1")  # query: ignored
            assert status == 200 and json.loads(body)["connections"] == 0
            # a standard client, through the HTTP library
            port = url.rsplit(":", 1)[1]
            reply = await asyncio.to_thread(urllib.request.urlopen,
                                            f"http://127.0.0.1:{port}/metrics", None, TIMEOUT)
            with reply:
                assert reply.status == 200
                assert b"posecast_frames_solved_total 0.0" in reply.read()
            with pytest.raises(urllib.error.HTTPError) as refused:
                await asyncio.to_thread(urllib.request.urlopen,
                                        f"http://127.0.0.1:{port}/nowhere", None, TIMEOUT)
            assert refused.value.code == 404
            # its socket, closed (websockets waits for a client's close, up to 10 s)
            refused.value.close()
            # websockets on the same port, on any path, as before
            for path in ("", "/metrics"):
                async with joined(url + path, "spectator", "w", "viewer") as ws:
                    assert isinstance(await next_of(ws, AvatarRoster), AvatarRoster)
            status, _, body = await http_get(url, "/healthz")
            assert status == 200 and json.loads(body)["connections"] == 0
        assert session.metrics.connections == 2  # the websockets alone

    asyncio.run(main())


def test_two_servers_in_one_process_show_their_own_figures(rig_session: Session,
                                                           walk: ViveRecording) -> None:
    """Each session scrapes its own registry (the process-wide default holds neither)."""
    busy, idle = fresh(rig_session), fresh(rig_session)

    async def main() -> None:
        async with serving(busy) as busy_url, serving(idle) as idle_url:
            async with joined(busy_url, "player", "r", "p") as player:
                await stream(player, walk, 5)
            while busy.metrics.frames_received < 5:  # read, and maybe queued for its handler
                await asyncio.sleep(0.01)
            busy_text = (await http_get(busy_url, "/metrics"))[2].decode()
            idle_text = (await http_get(idle_url, "/metrics"))[2].decode()
        assert samples(busy_text)[("posecast_frames_received_total", ())] == 5
        assert samples(idle_text)[("posecast_frames_received_total", ())] == 0

    asyncio.run(main())


@pytest.mark.parametrize("pending", [0, 1, 3, 4])
def test_histogram_buckets_are_inclusive_upper_bounds(pending: int) -> None:
    """Prometheus' "le": a value on a bound counts in that bound's bucket (held first or
    not: a batch larger than the buffer, one that fills it, one that overflows it)."""
    h = StageHistograms(("a", "b"), bounds=(0.001, 0.01), pending=pending)
    h.observe(np.array([[0.001, 0.0010001, 0.5, -0.002],
                        [0.0, 0.01, 0.01, 0.01]]))
    h.observe(np.array([[0.009], [2.0]]))
    assert h.counts.tolist() == [[2, 2, 1], [1, 3, 1]]
    buckets, total = h.cumulative("a")
    assert buckets == [("0.001", 2.0), ("0.01", 4.0), ("+Inf", 5.0)]
    assert total == pytest.approx(0.001 + 0.0010001 + 0.5 - 0.002 + 0.009)
    assert h.count("b") == 5 and h.cumulative("b")[1] == pytest.approx(2.03)


def test_the_servers_held_values_are_counted_when_read_or_when_the_buffer_fills() -> None:
    rng = np.random.default_rng(8)
    held, direct = ServerLatency(), StageHistograms(SERVER_STAGES)
    # ~60,000 frames: the buffer fills a few times; then one batch larger than it
    for n in [*rng.integers(1, 40, 3000).tolist(), SERVER_PENDING + 3616]:
        captured = rng.uniform(0.0, 1.0, n)
        received = captured + rng.exponential(0.001, n)
        solved, sent = received.max() + 0.0004, received.max() + 0.0006
        held.batch(captured, received, solved, sent)
        direct.observe(np.stack([received - captured, solved - received, sent - received]))
        if n == 7:  # a scrape between batches
            assert held.counts.tolist() == direct.counts.tolist()
    assert held.counts.tolist() == direct.counts.tolist()
    np.testing.assert_allclose(held.sums, direct.sums, rtol=1e-12)


def test_metrics_page_is_made_at_most_once_per_max_age() -> None:
    """A client asking in a loop gets the page made up to max_age_s before."""
    t, made = [0.0], [0]

    def page() -> Reply:
        made[0] += 1
        return Reply(f"page {made[0]}".encode(), "text/plain")

    route = Reused(page, 1.0, clock=lambda: t[0])
    bodies = []
    for when in (10.0, 10.5, 10.999, 11.0, 11.2, 9.0):  # the last: a clock gone back
        t[0] = when
        bodies.append(route().body)
    assert bodies == [b"page 1", b"page 1", b"page 1", b"page 2", b"page 2", b"page 3"]
