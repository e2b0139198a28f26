"""wss:// and --origins over real sockets on 127.0.0.1: a private CA and a server
certificate made here with the openssl command line, a player and a spectator that see
each other through TLS, clients that refuse what they must not trust, each failure as
one line, and the browser Origin allow-list."""

from __future__ import annotations

import asyncio
import contextlib
import shutil
import socket
import ssl
import subprocess
import threading
import time
from collections.abc import AsyncIterator, Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
from commands import CLIP, Command, status_lines
from conftest import SERVER_TIMEOUT, serving
from stream_decode import decode
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus
from websockets.typing import Origin

from posecast.client.bench.demo import HEADSET_HZ
from posecast.client.builtin import builtin_motion_path
from posecast.client.cli import main
from posecast.client.session.connection import SessionError, make_hello, open_session
from posecast.client.session.player import Player, Ticker
from posecast.client.session.spectator import Spectator
from posecast.client.sources import open_source
from posecast.client.sources.bvh_source import BvhSource
from posecast.protocol import PROTOCOL_VERSION, Hello, Welcome, encode
from posecast.protocol.arrivals import ArrivalStamps
from posecast.server.app import Session
from posecast.server.serving import run_server
from posecast.server.tls import TLSConfigError, check_origin, server_tls_context

OPENSSL = shutil.which("openssl")
ROOM = "tls"
TIMEOUT = 30.0  # generous: the machine is shared


@dataclass(frozen=True)
class Certs:
    ca: Path  # the private CA's certificate: what --cafile trusts
    cert: Path  # the server's, for 127.0.0.1 and localhost, signed by the CA
    key: Path
    other_key: Path  # a key of another certificate
    other_cert: Path  # signed by the CA, for other.example only
    encrypted_key: Path


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run([OPENSSL or "openssl", *args], cwd=cwd, check=True, capture_output=True,
                   timeout=60)


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Certs:
    if OPENSSL is None:
        pytest.skip("no openssl command line here: the tests make their certificates with it")
    d = tmp_path_factory.mktemp("tls")
    ec = ("-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1")
    _openssl("req", "-x509", *ec, "-nodes", "-keyout", "ca.key", "-out", "ca.pem",
             "-days", "2", "-subj", "/CN=posecast test CA",
             "-addext", "basicConstraints=critical,CA:TRUE",
             "-addext", "keyUsage=critical,keyCertSign,cRLSign", cwd=d)
    _openssl("req", *ec, "-nodes", "-keyout", "server.key", "-out", "server.csr",
             "-subj", "/CN=localhost", cwd=d)
    (d / "ext.cnf").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n"
                               "basicConstraints=CA:FALSE\nextendedKeyUsage=serverAuth\n")
    _openssl("x509", "-req", "-in", "server.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
             "-CAcreateserial", "-out", "server.pem", "-days", "2", "-extfile", "ext.cnf",
             cwd=d)
    _openssl("req", *ec, "-nodes", "-keyout", "other.key", "-out", "other.csr",
             "-subj", "/CN=other.example", cwd=d)
    (d / "other.cnf").write_text("subjectAltName=DNS:other.example\n"
                                 "basicConstraints=CA:FALSE\nextendedKeyUsage=serverAuth\n")
    _openssl("x509", "-req", "-in", "other.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
             "-CAcreateserial", "-out", "other.pem", "-days", "2", "-extfile", "other.cnf",
             cwd=d)
    _openssl("pkey", "-in", "server.key", "-aes256", "-passout", "pass:secret", "-out",
             "encrypted.key", cwd=d)
    return Certs(d / "ca.pem", d / "server.pem", d / "server.key", d / "other.key",
                 d / "other.pem", d / "encrypted.key")


@pytest.fixture(scope="module")
def session() -> Session:
    return Session(reconnect_grace=0.0)  # the rig and the warm solver: once


@contextlib.asynccontextmanager
async def tls_serving(session: Session, certs: Certs,
                      origins: Sequence[str] | None = None, cert: Path | None = None,
                      key: Path | None = None) -> AsyncIterator[int]:
    """A real wss:// server for ``session`` on a free port of 127.0.0.1; yields the port."""
    session.rooms.clear()
    stop = asyncio.Event()
    ready: asyncio.Future[int] = asyncio.get_running_loop().create_future()
    server = asyncio.create_task(run_server(
        "127.0.0.1", 0, session, stop, ready.set_result,
        tls=server_tls_context(cert or certs.cert, key or certs.key), origins=origins))
    port = await asyncio.wait_for(ready, SERVER_TIMEOUT)
    try:
        yield port
    finally:
        stop.set()
        await asyncio.wait_for(server, SERVER_TIMEOUT)


def _trusting(certs: Certs) -> ssl.SSLContext:
    return ssl.create_default_context(cafile=str(certs.ca))


# ------------------------------------------------------------------ over wss://
def test_a_player_and_a_spectator_see_each_other_over_wss(session: Session,
                                                          certs: Certs) -> None:
    async def main() -> tuple[Spectator, int, list[int], bool]:
        async with tls_serving(session, certs) as port:
            url = f"wss://localhost:{port}"
            spectator = Spectator(url, ROOM, "watcher", cafile=certs.ca)
            watching = asyncio.create_task(spectator.run())
            source = open_source(f"bvh:{builtin_motion_path()}")
            player = Player(url, ROOM, "ann", source, cafile=certs.ca)
            playing = asyncio.create_task(player.run(seconds=2.0))
            while not any(a.connected for a in session.rooms.get(ROOM, _Empty()).avatars
                          .values()):
                await asyncio.sleep(0.05)
            # the server's end of each connection, while both are on
            room = session.rooms[ROOM]
            (watched,) = [s.connection for s in room.spectators.values()]
            assert watched is not None
            sock = watched.transport.get_extra_info("socket")
            options = [sock.getsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF),
                       sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NOTSENT_LOWAT)]
            (avatar,) = room.avatars.values()
            stamped = isinstance(avatar.connection, ArrivalStamps) and \
                avatar.connection.fast_path is not None
            stats = await asyncio.wait_for(playing, TIMEOUT)
            source.close()
            await asyncio.sleep(0.2)  # the last batches on their way
            watching.cancel()
            with contextlib.suppress(asyncio.CancelledError, SessionError):
                await watching
            return spectator, stats.frames_sent, options, stamped

    spectator, sent, (sndbuf, unsent), stamped = asyncio.run(main())
    limits = session.limits
    # the socket options reach the TCP socket under TLS (Linux doubles SO_SNDBUF)
    assert limits.send_buffer_bytes <= sndbuf <= 2 * limits.send_buffer_bytes
    assert unsent == limits.send_unsent_bytes
    # the player's frames are read with their arrival stamps, on the fast path
    assert stamped
    received = spectator.stats.frames_received
    assert sent > 100 and received > 0.9 * sent, (sent, received)
    summary = spectator.stats.latency.summary()
    for stage in ("capture_to_server", "server", "capture_to_spectator"):
        assert stage in summary, summary
        assert 0.0 < summary[stage]["p50"] < 1000.0, (stage, summary[stage])
    print(f"over wss:// on 127.0.0.1: {received} of {sent} frames, "
          + ", ".join(f"{s} p50 {summary[s]['p50']:.2f} ms p99 {summary[s]['p99']:.2f} ms"
                      for s in ("capture_to_server", "server", "capture_to_spectator")))


async def _players(url: str, players: int, seconds: float, cafile: Path | None) -> None:
    """Players replaying the built-in walk on one schedule, as the demo's, over ``url``."""
    sources = [BvhSource(builtin_motion_path(), loop=True, rate_hz=HEADSET_HZ,
                         offset=(1.5 * i, 0.0), start_frame=37 * i) for i in range(players)]
    ticker = Ticker(HEADSET_HZ)
    try:
        await asyncio.gather(*(Player(url, "demo", f"player {i + 1}", source, ticker=ticker,
                                      cafile=cafile).run(seconds)
                               for i, source in enumerate(sources)))
    finally:
        for source in sources:
            source.close()


class _Empty:
    avatars: ClassVar[dict[int, object]] = {}


def _join_error(url: str, cafile: Path | None = None) -> str:
    async def main() -> str:
        with pytest.raises(SessionError) as refused:
            await open_session(url, make_hello(url, "spectator", ROOM, "x"), cafile=cafile,
                               timeout=TIMEOUT)
        return str(refused.value)
    return asyncio.run(main())


def test_without_cafile_a_private_ca_is_not_trusted(session: Session, certs: Certs) -> None:
    async def main() -> str:
        async with tls_serving(session, certs) as port:
            url = f"wss://127.0.0.1:{port}"
            with pytest.raises(SessionError) as refused:
                await open_session(url, make_hello(url, "spectator", ROOM, "x"))
            return str(refused.value)

    why = asyncio.run(main())
    assert "the server's certificate is not trusted" in why and "--cafile" in why, why
    assert "\n" not in why


def test_a_certificate_for_another_host_is_not_trusted(session: Session,
                                                       certs: Certs) -> None:
    async def main() -> str:
        async with tls_serving(session, certs, cert=certs.other_cert,
                               key=certs.other_key) as port:
            url = f"wss://localhost:{port}"  # the certificate is for other.example
            with pytest.raises(SessionError) as refused:
                await open_session(url, make_hello(url, "spectator", ROOM, "x"),
                                   cafile=certs.ca)
            return str(refused.value)

    why = asyncio.run(main())
    assert "not trusted" in why and "localhost" in why, why


def test_ws_to_a_tls_server_and_wss_to_a_plain_one_each_say_what_to_use(
        session: Session, certs: Certs) -> None:
    async def main() -> tuple[str, str]:
        async with tls_serving(session, certs) as port:
            url = f"ws://127.0.0.1:{port}"
            with pytest.raises(SessionError) as plain_to_tls:
                await open_session(url, make_hello(url, "spectator", ROOM, "x"),
                                   timeout=TIMEOUT)
        async with serving(session) as plain_url:
            url = plain_url.replace("ws://", "wss://")
            with pytest.raises(SessionError) as tls_to_plain:
                await open_session(url, make_hello(url, "spectator", ROOM, "x"),
                                   cafile=certs.ca, timeout=TIMEOUT)
        return str(plain_to_tls.value), str(tls_to_plain.value)

    plain_to_tls, tls_to_plain = asyncio.run(main())
    assert "use wss://" in plain_to_tls, plain_to_tls
    assert "use ws://" in tls_to_plain, tls_to_plain


# ------------------------------------------------------------------ origins
def test_an_origin_off_the_list_is_refused_and_one_on_it_is_let_in(session: Session,
                                                                  certs: Certs) -> None:
    async def hello(port: int, origin: str | None) -> object:
        async with connect(f"wss://localhost:{port}", ssl=_trusting(certs),
                           origin=None if origin is None else Origin(origin),
                           compression=None) as ws:
            await ws.send(encode(Hello(protocol_version=PROTOCOL_VERSION,
                                       role="spectator", room=ROOM, display_name="page")))
            return decode(await asyncio.wait_for(ws.recv(), TIMEOUT))

    async def main() -> tuple[object, object, int]:
        async with tls_serving(session, certs, origins=["https://a.example",
                                                        "http://localhost:8000"]) as port:
            on_list = await hello(port, "https://a.example")
            no_origin = await hello(port, None)  # our own clients send none
            with pytest.raises(InvalidStatus) as refused:
                await hello(port, "https://evil.example")
            return on_list, no_origin, refused.value.response.status_code

    on_list, no_origin, status = asyncio.run(main())
    assert isinstance(on_list, Welcome) and isinstance(no_origin, Welcome)
    assert status == 403


def test_origins_are_scheme_host_and_port() -> None:
    assert check_origin("https://A.example:8443") == "https://a.example:8443"
    assert check_origin("http://[::1]:8000") == "http://[::1]:8000"
    for bad in ("a.example", "https://a.example/", "https://a.example/page", "ftp://a",
                "https://a.example:99999", "https://"):
        with pytest.raises(ValueError):
            check_origin(bad)


# ------------------------------------------------------------------ the server's files
def test_files_that_cannot_serve_tls_are_one_line_each(certs: Certs, tmp_path: Path) -> None:
    not_pem = tmp_path / "notes.txt"
    not_pem.write_text("hello\n")
    cases = [
        ((certs.cert, certs.other_key), "is not the key of the certificate"),
        ((certs.cert, certs.encrypted_key), "encrypted"),
        ((not_pem, certs.key), "no PEM certificate"),
        ((certs.cert, not_pem), "no PEM private key"),
        ((certs.key, certs.key), "no PEM certificate"),
        ((tmp_path / "missing.pem", certs.key), "cannot read --certfile"),
    ]
    for (cert, key), words in cases:
        with pytest.raises(TLSConfigError) as refused:
            server_tls_context(cert, key)
        assert words in str(refused.value) and "\n" not in str(refused.value), (
            cert, key, refused.value)
    context = server_tls_context(certs.cert, certs.key)
    assert context.minimum_version >= ssl.TLSVersion.TLSv1_2


# ------------------------------------------------------------------ the CLI
def _usage_line(err: str, command: str, words: str) -> None:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"posecast {command}: "), err
    assert words in lines[0], err


@pytest.mark.parametrize(("argv", "words"), [
    (["serve", "--keyfile", "/no/such.key"], "--keyfile"),
    (["serve", "--certfile", "/no/such.pem"], "--certfile"),
    (["serve", "--origins", "ftp://a.example"], "--origins"),
    (["serve", "--origins", "https://a.example/page"], "--origins"),
    (["serve", "--origins", "https://a.example,b.example"], "--origins"),
    (["play", "--server", "wss://127.0.0.1:8765", "--room", "r", "--cafile",
      "/no/such.pem"], "--cafile"),
    (["view", "--server", "wss://127.0.0.1:8765", "--room", "r", "--cafile", "{notes}"],
     "--cafile is not a PEM file"),
])
def test_a_bad_tls_option_is_one_line_and_status_2(argv: list[str], words: str,
                                                   tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]
                                                   ) -> None:
    notes = tmp_path / "notes.txt"
    notes.write_text("not a certificate\n")
    with pytest.raises(SystemExit) as exit_info:
        main([a.replace("{notes}", str(notes)) for a in argv])
    assert exit_info.value.code == 2
    captured = capsys.readouterr()
    _usage_line(captured.err, argv[0], words)
    assert captured.out == ""


def test_tls_files_that_do_not_go_together_are_one_line_and_status_2(
        certs: Certs, capsys: pytest.CaptureFixture[str]) -> None:
    cases = [
        (["serve", "--certfile", str(certs.cert)], "--certfile needs --keyfile"),
        (["serve", "--keyfile", str(certs.key)], "--keyfile needs --certfile"),
        (["serve", "--certfile", str(certs.cert), "--keyfile", str(certs.other_key)],
         "is not the key of the certificate"),
        (["play", "--server", "ws://127.0.0.1:8765", "--room", "r", "--source", CLIP,
          "--cafile", str(certs.ca)], "--cafile is for wss://"),
    ]
    for argv, words in cases:
        assert main(argv) == 2, argv  # before any server starts or any socket opens
        captured = capsys.readouterr()
        _usage_line(captured.err, argv[0], words)


def test_play_and_view_over_wss_through_the_cli(certs: Certs, egl: None,
                                                tmp_path: Path) -> None:
    """posecast serve with a certificate, play and view with --cafile: they see each
    other; play without --cafile is one line, status 1."""
    serve = Command("serve", "--port", "0", "--certfile", str(certs.cert), "--keyfile",
                    str(certs.key), "--origins", "https://a.example", cwd=tmp_path)
    try:
        listening = serve.wait_for("posecast server on wss://")
        port = int(listening.rsplit(":", 1)[1])
        url = f"wss://localhost:{port}"
        code, out, err = Command("play", "--server", url, "--room", ROOM, "--source", CLIP,
                                 "--seconds", "1", cwd=tmp_path).finish()
        assert code == 1 and "Traceback" not in out + err
        (line,) = status_lines(err)
        assert line.startswith(f"posecast play: cannot reach {url}: the server's "
                               "certificate is not trusted"), err
        play = Command("play", "--server", url, "--room", ROOM, "--source", CLIP,
                       "--loop", "--seconds", "60", "--cafile", str(certs.ca), cwd=tmp_path)
        play.wait_for("joined room")
        frames = tmp_path / "frames"
        code, out, err = Command("view", "--headless", "--server", url, "--room", ROOM,
                                 "--frames", "5", "--out", str(frames), "--cafile",
                                 str(certs.ca), cwd=tmp_path).finish()
        assert code == 0 and "Traceback" not in out + err, err
        assert len(list(frames.glob("*.png"))) == 5, out
        code, out, err = play.interrupt()
        assert code == 130 and "Traceback" not in err, err
    finally:
        code, out, err = serve.interrupt()
    assert "Traceback" not in err, err


def _loops() -> dict[str, Callable[[], asyncio.AbstractEventLoop]]:
    loops: dict[str, Callable[[], asyncio.AbstractEventLoop]] = {
        "asyncio": asyncio.new_event_loop}
    with contextlib.suppress(ImportError):  # serve runs on uvloop where it is installed
        import uvloop
        loops["uvloop"] = uvloop.new_event_loop
    return loops


@pytest.mark.parametrize("loop", list(_loops()))
def test_a_slow_viewer_over_wss_is_not_further_behind(session: Session, certs: Certs,
                                                      loop: str) -> None:
    """A viewer that reads one batch per 75 ms through a small receive buffer: over TLS
    the server must still see its backlog (``_cap_send_buffers``: the TLS layer's mark
    and the TCP transport's under it), so that latest-wins keeps it about as close to
    the newest pose as over ws://. Before: nothing after the welcome (a mark of 0 paused
    the TLS layer for good), then 1.85 s / 2.6 s behind and growing (the 64 KiB under
    the TLS layer); now ~0.7 s / 0.8 s, ws:// ~0.46 s / 0.6 s."""
    from posecast.server.clock import now

    players, seconds, read_every = 8, 4.0, 0.075

    async def behind(port: int, secure: bool) -> list[float]:
        sock = socket.socket()
        # ~4 batches of 8 coded avatars (protocol 4's ~1 KB; 4096 bytes held ~4 of
        # protocol 3's 2.7 KB batches), here and in the TLS layer's read-ahead below
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 2048)
        await asyncio.get_running_loop().sock_connect(sock, ("127.0.0.1", port))
        scheme = "wss" if secure else "ws"
        viewer = await connect(f"{scheme}://localhost:{port}", sock=sock,
                               ssl=_trusting(certs) if secure else None,
                               compression=None, max_size=None, max_queue=1,
                               close_timeout=1.0)  # its close waits behind its backlog
        if secure:  # the client's TLS layer reads 256 KiB ahead unless told: this test is
            # about what the server holds back, as on a slow link
            viewer.transport.set_read_buffer_limits(high=2048)
        await viewer.send(encode(Hello(protocol_version=PROTOCOL_VERSION, role="spectator",
                                       room="demo", display_name="slow")))
        lags: list[float] = []

        async def read_slowly() -> None:
            while True:
                msg = decode(await viewer.recv())
                t_capture = getattr(msg, "t_capture", None)
                if t_capture is not None and len(t_capture):
                    lags.append(now() - float(np.max(t_capture)))
                await asyncio.sleep(read_every)

        reader = asyncio.create_task(read_slowly())
        url = f"{scheme}://localhost:{port}"
        await _players(url, players, seconds, certs.ca if secure else None)
        reader.cancel()
        await viewer.close()
        return lags[len(lags) // 3:]

    async def main() -> tuple[list[float], list[float]]:
        async with serving(session) as plain_url:
            plain = await behind(int(plain_url.rsplit(":", 1)[1]), False)
        async with tls_serving(session, certs) as port:
            secure = await behind(port, True)
        return plain, secure

    with asyncio.Runner(loop_factory=_loops()[loop]) as runner:
        plain, secure = runner.run(main())
    print(f"{loop}: slow viewer, {players} players, one batch per {read_every * 1000:.0f} ms, "
          f"behind by (median / max): ws:// {np.median(plain):.2f} s / {max(plain):.2f} s, "
          f"wss:// {np.median(secure):.2f} s / {max(secure):.2f} s")
    assert max(secure) < 1.0, [round(x, 3) for x in secure]


def test_a_viewer_that_draws_slowly_over_wss_shows_poses_a_draw_old(session: Session,
                                                                   certs: Certs) -> None:
    """posecast's own viewer takes everything that arrived before each draw
    (``Session.catch_up``); the bytes the client's TLS layer reads ahead are taken too:
    drawing every 75 ms beside 8 players, the newest pose drawn is ~5 ms old (median),
    as over ws://, not the backlog of its buffers."""
    from posecast.server.clock import now

    lags: list[float] = []
    stop = threading.Event()

    def slow_viewer(url: str) -> None:  # its own thread and loop, like a viewer process
        async def view() -> None:
            spectator = Spectator(url, "demo", "slow viewer", cafile=certs.ca)
            receiving = asyncio.create_task(spectator.run())
            while not stop.is_set():
                newest = [b.t_capture[r] for b, r, _ in spectator.latest.values()]
                if newest:
                    lags.append(now() - float(max(newest)))
                time.sleep(0.075)  # the draw: nothing else runs in this loop meanwhile
                await spectator.catch_up()
            receiving.cancel()
            with contextlib.suppress(asyncio.CancelledError, SessionError):
                await receiving
        asyncio.run(view())

    async def main() -> None:
        async with tls_serving(session, certs) as port:
            url = f"wss://localhost:{port}"
            viewer = threading.Thread(target=slow_viewer, args=(url,))
            viewer.start()
            try:
                await _players(url, 8, 4.0, certs.ca)
            finally:
                stop.set()
                await asyncio.to_thread(viewer.join)

    asyncio.run(main())
    assert len(lags) > 20
    settled = lags[len(lags) // 3:]
    print(f"viewer drawing every 75 ms over wss://, 8 players: newest pose drawn "
          f"{np.median(settled) * 1000:.0f} ms old (median), {max(settled) * 1000:.0f} ms max")
    assert max(settled) < 0.2, [round(x, 3) for x in settled]
