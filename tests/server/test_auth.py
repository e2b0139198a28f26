"""Rooms with a secret: join tokens (server.auth) minted by `posecast token`, checked by
the server at hello over real sockets on 127.0.0.1 (ws:// and wss://, with a certificate
made here), and each refusal one clear line, in the protocol's Error and on the command
line."""

from __future__ import annotations

import asyncio
import logging
import os
import shutil
import socket
import ssl
import subprocess
import sys
import time
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path

import jwt
import pytest
from stream_decode import decode
from websockets.asyncio.client import connect

from posecast.client.builtin import builtin_motion_path
from posecast.client.cli import main
from posecast.client.cli.arguments import duration
from posecast.client.session.connection import Reconnect, SessionError, make_hello, open_session
from posecast.client.session.player import Player
from posecast.client.session.spectator import Spectator
from posecast.client.session.tls import client_tls_context
from posecast.client.sources import open_source
from posecast.protocol import Error, ErrorCode, encode
from posecast.server.app import Session
from posecast.server.auth import (
    MIN_SECRET_BYTES,
    SECRET_ENV,
    JoinTokens,
    SecretError,
    TokenError,
    is_loopback,
    load_secret,
    read_secret_file,
)
from posecast.server.serving import run_server
from posecast.server.tls import server_tls_context

SECRET = b"s3cret-of-this-test-server-0123456789abcdef"  # 42 bytes
OTHER_SECRET = b"another-server-s-secret-0123456789abcdefgh"
CLIP = f"bvh:{builtin_motion_path()}"
WAIT = 120.0  # seconds for a subprocess to get somewhere (imports, kernels from cache)
T0 = 1_800_000_000.0  # a fixed "now" for the pure tests


@pytest.fixture(scope="module")
def session() -> Session:
    return Session(reconnect_grace=0.0, tokens=JoinTokens(SECRET))


@pytest.fixture(scope="module")
def certificate(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A self-signed certificate for 127.0.0.1 and its key: the certificate is its own
    CA, the client's --cafile."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed: it makes the test certificate")
    folder = tmp_path_factory.mktemp("tls")
    cert, key = folder / "cert.pem", folder / "key.pem"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt",
                    "ec_paramgen_curve:prime256v1", "-nodes", "-keyout", str(key), "-out",
                    str(cert), "-days", "2", "-subj", "/CN=localhost", "-addext",
                    "subjectAltName=IP:127.0.0.1,DNS:localhost"],
                   check=True, capture_output=True, timeout=60)
    return cert, key


# --------------------------------------------------------------------------- pure
def test_a_minted_token_grants_its_room_role_and_expiry() -> None:
    tokens = JoinTokens(SECRET)
    token = tokens.mint("lobby", "player", 7200, now=T0)
    grant = tokens.verify(token, "lobby", "player", "ana", now=T0 + 7199)
    assert (grant.room, grant.role, grant.expires, grant.name) == (
        "lobby", "player", T0 + 7200, None)
    # a JWT any library reads: HS256 with the claims the docs name
    assert jwt.get_unverified_header(token)["alg"] == "HS256"
    claims = jwt.decode(token, SECRET, algorithms=["HS256"], options={"verify_exp": False,
                                                                   "verify_iat": False})
    assert claims == {"room": "lobby", "role": "player", "iat": T0, "exp": T0 + 7200}


def refusal(token: str | None, room: str = "lobby", role: str = "player",
            name: str = "ana", now: float = T0) -> str:
    with pytest.raises(TokenError) as refused:
        JoinTokens(SECRET).verify(token, room, role, name, now=now)
    reason = str(refused.value)
    assert "\n" not in reason
    return reason


def test_each_refusal_names_its_reason() -> None:
    tokens, other = JoinTokens(SECRET), JoinTokens(OTHER_SECRET)
    assert "not signed with this server's secret" in refusal(
        other.mint("lobby", "player", 60, now=T0))
    expired = refusal(tokens.mint("lobby", "player", 3600, now=T0 - 7200))
    assert "expired at 2027-01-15 07:00:00 UTC (60 min ago)" in expired, expired
    assert "is for room 'attic', not 'lobby'" in refusal(tokens.mint("attic", "player", 60,
                                                                     now=T0))
    assert "is for a spectator, not a player" in refusal(tokens.mint("lobby", "spectator", 60,
                                                                     now=T0))
    # a player's token admits them as a spectator of the same room (their headset's
    # view of it, play --hmd), and of no other room
    player = tokens.mint("lobby", "player", 60, name="ana", now=T0)
    assert tokens.verify(player, "lobby", "spectator", "ana", now=T0).role == "player"
    with pytest.raises(TokenError, match="is for room 'lobby', not 'attic'"):
        tokens.verify(player, "attic", "spectator", "ana", now=T0)
    assert "needs a join token" in refusal(None)
    for garbage in ("1", "garbage", "a.b.c", "x" * 1000):
        assert "malformed" in refusal(garbage)
    unsigned = jwt.encode({"room": "lobby", "role": "player", "exp": T0 + 60, "iat": T0},
                          None, algorithm="none")
    assert "not signed with HS256" in refusal(unsigned)
    assert "for the name 'bo', not 'ana'" in refusal(tokens.mint("lobby", "player", 60,
                                                                 name="bo", now=T0))


def test_claims_a_web_site_got_wrong_are_named() -> None:
    def signed(**claims: object) -> str:
        return jwt.encode({"room": "lobby", "role": "player", "exp": T0 + 60, "iat": T0,
                           **claims}, SECRET, algorithm="HS256")

    no_exp = jwt.encode({"room": "lobby", "role": "player", "iat": T0}, SECRET,
                        algorithm="HS256")
    assert "no 'exp' claim" in refusal(no_exp)
    assert "'role' claim must be player or spectator" in refusal(signed(role="admin"))
    assert "'exp' claim is not a unix time" in refusal(signed(exp="tomorrow"))
    assert "'room' claim is not text" in refusal(signed(room=["lobby"]))
    assert "ahead of this server's clock" in refusal(signed(iat=T0 + 600, exp=T0 + 900))


def test_clock_skew_within_the_leeway_is_forgiven() -> None:
    tokens = JoinTokens(SECRET, leeway_s=5.0)
    token = tokens.mint("lobby", "player", 60, now=T0)
    tokens.verify(token, "lobby", "player", now=T0 + 64)  # 4 s past its expiry
    tokens.verify(token, "lobby", "player", now=T0 - 4)  # issued 4 s "in the future"
    with pytest.raises(TokenError, match="expired"):
        tokens.verify(token, "lobby", "player", now=T0 + 66)


def test_the_secret_comes_from_a_file_or_the_environment(tmp_path: Path) -> None:
    path = tmp_path / "secret"
    path.write_bytes(SECRET + b"\n")  # as `echo` writes it
    assert read_secret_file(path) == SECRET
    assert load_secret(path, {SECRET_ENV: OTHER_SECRET.decode()}) == SECRET  # the file wins
    assert load_secret(None, {SECRET_ENV: OTHER_SECRET.decode()}) == OTHER_SECRET
    assert load_secret(None, {}) is None  # open
    short = tmp_path / "short"
    short.write_bytes(b"x" * (MIN_SECRET_BYTES - 1) + b"\n")
    empty = tmp_path / "empty"
    empty.write_bytes(b"\n")
    for where, why in [(short, "31 bytes; use 32 or more"), (empty, "is empty"),
                       (tmp_path / "missing", "no such secret file"),
                       (tmp_path, "is a folder")]:
        with pytest.raises(SecretError, match=why):
            read_secret_file(where)
    with pytest.raises(SecretError, match=f"{SECRET_ENV} is 5 bytes"):
        load_secret(None, {SECRET_ENV: "hello"})


def test_durations() -> None:
    assert [duration(t) for t in ("90s", "15m", "2h", "7d", "3600", "1.5h")] == [
        90.0, 900.0, 7200.0, 604800.0, 3600.0, 5400.0]
    for bad in ("", "h", "2x", "-1h", "0", "nan", "inf", "400d"):
        with pytest.raises(Exception, match="must be"):
            duration(bad)


def test_loopback_hosts() -> None:
    assert all(map(is_loopback, ["127.0.0.1", "127.0.0.2", "::1", "localhost"]))
    assert not any(map(is_loopback, ["0.0.0.0", "::", "", "192.168.1.4", "example.org"]))


# --------------------------------------------------------------------------- sockets
def run(session: Session, test: Callable[[str], Awaitable[None]],
        tls: ssl.SSLContext | None = None) -> None:
    """Serve ``session`` on a free port of 127.0.0.1 (wss:// with ``tls``), run the test
    against its URL, shut down cleanly."""
    async def main() -> None:
        session.rooms.clear()
        stop = asyncio.Event()
        ready: asyncio.Future[int] = asyncio.get_running_loop().create_future()
        server = asyncio.create_task(run_server("127.0.0.1", 0, session, stop,
                                                ready.set_result, tls=tls))
        port = await asyncio.wait_for(ready, 30)
        try:
            await asyncio.wait_for(test(f"{'ws' if tls is None else 'wss'}://127.0.0.1:"
                                        f"{port}"), 60)
        finally:
            stop.set()
            await asyncio.wait_for(server, 30)
    asyncio.run(main())


@pytest.fixture(params=["ws", "wss"])
def scheme(request: pytest.FixtureRequest, certificate: tuple[Path, Path]
           ) -> tuple[ssl.SSLContext | None, Path | None]:
    """The server's TLS context and the client's CA file: (None, None) for ws://."""
    if request.param == "ws":
        return None, None
    cert, key = certificate
    return server_tls_context(cert, key), cert


def test_valid_tokens_join_and_the_spectator_sees_the_player(
        session: Session, scheme: tuple[ssl.SSLContext | None, Path | None]) -> None:
    tokens = JoinTokens(SECRET)
    tls, cafile = scheme

    async def test(url: str) -> None:
        spectator = Spectator(url, "lobby", "watcher",
                              token=tokens.mint("lobby", "spectator", 60), cafile=cafile)
        player = Player(url, "lobby", "ana", open_source(CLIP, loop=True),
                        token=tokens.mint("lobby", "player", 60, name="ana"), cafile=cafile)
        stop = asyncio.Event()
        watching = asyncio.create_task(spectator.run(stop=stop))
        playing = asyncio.create_task(player.run(stop=stop))
        try:
            while (player.stats.avatar_id is None or spectator.stats.frames_per_avatar[
                    player.stats.avatar_id] < 20):
                assert not watching.done() and not playing.done()
                await asyncio.sleep(0.05)
        finally:
            stop.set()
            await asyncio.gather(watching, playing)
        assert spectator.stats.frames_per_avatar[player.stats.avatar_id] >= 20

    rejected = session.metrics.rejected[ErrorCode.AUTH_FAILED]
    run(session, test, tls)
    assert session.metrics.rejected[ErrorCode.AUTH_FAILED] == rejected


def _bad_tokens() -> list[tuple[str, str | None, str, str]]:
    """(case, token, role, the reason's words), for a join to room 'lobby'."""
    tokens, other = JoinTokens(SECRET), JoinTokens(OTHER_SECRET)
    return [
        ("wrong secret", other.mint("lobby", "player", 60), "player",
         "not signed with this server's secret"),
        ("expired", tokens.mint("lobby", "player", 60, now=time.time() - 3600), "player",
         "the join token expired at"),
        ("wrong room", tokens.mint("attic", "spectator", 60), "spectator",
         "is for room 'attic', not 'lobby'"),
        ("wrong role", tokens.mint("lobby", "spectator", 60), "player",
         "is for a spectator, not a player"),
        ("missing", None, "spectator", "needs a join token"),
        ("client-chosen", "1", "player", "malformed"),
        ("garbage", "\x00not a jwt at all\x7f", "player", "malformed"),
    ]


def test_every_bad_token_is_refused_with_its_reason(
        session: Session, scheme: tuple[ssl.SSLContext | None, Path | None]) -> None:
    cases = _bad_tokens()
    tls, cafile = scheme

    async def test(url: str) -> None:
        for case, token, role, words in cases:
            hello = make_hello(url, role, "lobby", "mallory", token)  # type: ignore[arg-type]
            with pytest.raises(SessionError) as refused:
                await open_session(url, hello, cafile=cafile)
            assert refused.value.code == ErrorCode.AUTH_FAILED, case
            assert words in str(refused.value), (case, str(refused.value))
            assert "\n" not in str(refused.value)
        # and then the server closes with 1008, the reason the code
        async with connect(url, ssl=None if cafile is None
                           else client_tls_context(cafile)) as ws:
            await ws.send(encode(make_hello(url, "player", "lobby", "mallory", "1")))
            error = decode(await asyncio.wait_for(ws.recv(), 10))
            assert isinstance(error, Error) and error.code == ErrorCode.AUTH_FAILED
            await asyncio.wait_for(ws.wait_closed(), 10)
            assert (ws.close_code, ws.close_reason) == (1008, "auth_failed")
        assert not session.rooms  # no refused join made a room

    rejected = session.metrics.rejected[ErrorCode.AUTH_FAILED]
    run(session, test, tls)
    assert session.metrics.rejected[ErrorCode.AUTH_FAILED] == rejected + len(cases) + 1


def test_a_guessed_token_never_reaches_a_players_avatar(session: Session) -> None:
    """A player is in; a second client with a client-chosen token, a token of another
    server, or a spectator's token cannot join as a player: the first keeps its
    connection and its avatar, and the room has one avatar."""
    tokens = JoinTokens(SECRET)
    guesses = ["1", "ana", tokens.mint("lobby", "spectator", 60),
               JoinTokens(OTHER_SECRET).mint("lobby", "player", 60, name="ana")]

    async def test(url: str) -> None:
        owner = await open_session(url, make_hello(
            url, "player", "lobby", "ana", tokens.mint("lobby", "player", 60)))
        async with owner:
            for guess in guesses:
                with pytest.raises(SessionError, match="auth_failed"):
                    await open_session(url, make_hello(url, "player", "lobby", "ana", guess))
            room = session.rooms["lobby"]
            assert [a.avatar_id for a in room.avatars.values()] == [owner.avatar_id]
            assert all(a.connected for a in room.avatars.values())
            assert owner.ws.close_code is None  # not kicked

    run(session, test)


def test_a_reconnect_is_a_join_its_token_must_still_be_valid(session: Session) -> None:
    """A player whose connection is lost comes back with its token; once that token has
    expired the server refuses it, and the player stops with the reason, not retrying."""
    clock = [time.time()]
    expiring = Session(session.rig, reconnect_grace=30.0,
                       tokens=JoinTokens(SECRET, leeway_s=0.0, clock=lambda: clock[0]))
    tokens = JoinTokens(SECRET)
    said: list[str] = []

    async def test(url: str) -> None:
        player = Player(url, "lobby", "ana", open_source(CLIP, loop=True),
                        token=tokens.mint("lobby", "player", 60, now=clock[0]),
                        reconnect=Reconnect(say=said.append, first_s=0.05))
        playing = asyncio.create_task(player.run())
        sent = 0
        for expired in (False, True):
            while player.stats.frames_sent < sent + 10 or not expiring.rooms:
                assert not playing.done()
                await asyncio.sleep(0.05)
            clock[0] += 120.0 if expired else 30.0  # past the token's minute, or within
            (owner,) = expiring._owners.values()
            await owner.close(1012, "restarting")  # a drop the player reconnects after
            if not expired:
                while player.stats.reconnects == 0:
                    assert not playing.done()
                    await asyncio.sleep(0.05)
                sent = player.stats.frames_sent  # and it streams again in the new session
        with pytest.raises(SessionError, match="auth_failed: the join token expired at"):
            await playing

    run(expiring, test)
    assert said[0].startswith("connection lost") and "reconnected after" in said[1], said
    assert expiring.metrics.rejected[ErrorCode.AUTH_FAILED] >= 1


def test_an_open_server_says_so_and_warns_beyond_loopback(
        session: Session, caplog: pytest.LogCaptureFixture) -> None:
    async def start_and_stop(host: str, open_session: Session) -> None:
        stop = asyncio.Event()
        server = asyncio.create_task(run_server(host, 0, open_session, stop,
                                                lambda _port: stop.set()))
        await asyncio.wait_for(server, 30)

    open_server = Session(session.rig, reconnect_grace=0.0)
    with caplog.at_level(logging.INFO, logger="posecast.server"):
        asyncio.run(start_and_stop("127.0.0.1", open_server))
    lines = [r.getMessage() for r in caplog.records]
    assert "open: anyone can join any room; --secret-file to require tokens" in lines
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="posecast.server"):
        asyncio.run(start_and_stop("0.0.0.0", open_server))
    (warning,) = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert "listening on 0.0.0.0 without a secret" in warning
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="posecast.server"):
        asyncio.run(start_and_stop("127.0.0.1", session))
    assert not any("open:" in r.getMessage() for r in caplog.records)
    assert any("join tokens required" in r.getMessage() for r in caplog.records)


# --------------------------------------------------------------------------- the CLI
def posecast(*args: str, env: dict[str, str] | None = None, cwd: Path | None = None,
             ) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "posecast.client.cli", *args],
                          capture_output=True, text=True, timeout=WAIT, cwd=cwd,
                          env={**os.environ, **(env or {})})


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def secret_file(tmp_path: Path) -> Path:
    path = tmp_path / "secret"
    path.write_bytes(SECRET + b"\n")
    return path


@pytest.fixture
def served(secret_file: Path, certificate: tuple[Path, Path], tmp_path: Path
           ) -> Iterator[str]:
    """`posecast serve --secret-file` over TLS in a subprocess; yields its wss:// URL."""
    port = _free_port()
    log = (tmp_path / "serve.log").open("w")
    cert, key = certificate
    proc = subprocess.Popen([sys.executable, "-m", "posecast.client.cli", "serve",
                             "--port", str(port), "--secret-file", str(secret_file),
                             "--certfile", str(cert), "--keyfile", str(key)],
                            stdout=subprocess.DEVNULL, stderr=log, text=True,
                            env={k: v for k, v in os.environ.items() if k != SECRET_ENV})
    try:
        deadline = time.monotonic() + WAIT
        while time.monotonic() < deadline:  # until it listens
            assert proc.poll() is None, (tmp_path / "serve.log").read_text()
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", port)) == 0:
                    break
            time.sleep(0.1)
        else:
            pytest.fail("posecast serve did not start listening")
        yield f"wss://127.0.0.1:{port}"
    finally:
        proc.terminate()
        proc.wait(30)
        log.close()
    assert "join tokens required" in (tmp_path / "serve.log").read_text()


def test_posecast_token_prints_only_a_token_the_server_accepts(secret_file: Path) -> None:
    proc = posecast("token", "--secret-file", str(secret_file), "--room", "lobby",
                    "--role", "spectator", "--ttl", "15m")
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    token = proc.stdout.removesuffix("\n")
    assert proc.stdout.count("\n") == 1 and token.count(".") == 2
    grant = JoinTokens(SECRET).verify(token, "lobby", "spectator")
    assert 900 - 60 <= grant.expires - time.time() <= 900
    # the secret from the environment mints the same kind of token
    proc = posecast("token", "--room", "lobby", "--role", "player",
                    env={SECRET_ENV: SECRET.decode()})
    assert proc.returncode == 0, proc.stderr
    assert JoinTokens(SECRET).verify(proc.stdout.strip(), "lobby", "player").role == "player"


def _refusal_line(proc: subprocess.CompletedProcess[str]) -> str:
    """The one line a refused join prints (a cold kernel cache may add a notice)."""
    assert proc.returncode == 1 and "Traceback" not in proc.stderr + proc.stdout
    lines = [line for line in proc.stderr.splitlines()
             if line.strip() and not line.startswith(("posecast: compil", " "))]
    assert len(lines) == 1, proc.stderr
    return lines[0]


def test_play_over_wss_with_a_bad_token_is_one_line_and_a_good_one_plays(
        served: str, secret_file: Path, certificate: tuple[Path, Path],
        tmp_path: Path) -> None:
    cafile = str(certificate[0])
    bad = JoinTokens(OTHER_SECRET).mint("lobby", "player", 60)
    line = _refusal_line(posecast("play", "--server", served, "--room", "lobby", "--source",
                                  CLIP, "--cafile", cafile, "--token", bad, "--seconds", "5",
                                  cwd=tmp_path))
    assert line.startswith(f"posecast play: {served}: the server refused to join: "
                           "auth_failed: the join token is not signed with this "
                           "server's secret"), line
    good = posecast("token", "--secret-file", str(secret_file), "--room", "lobby",
                    "--role", "player").stdout.strip()
    proc = posecast("play", "--server", served, "--room", "lobby", "--source", CLIP,
                    "--cafile", cafile, "--token", good, "--seconds", "1", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "joined room 'lobby'" in proc.stderr and proc.stdout.startswith("sent ")


def test_view_over_wss_sees_a_player_with_tokens_and_bad_ones_are_one_line(
        served: str, egl: None, certificate: tuple[Path, Path], tmp_path: Path) -> None:
    tokens, cafile = JoinTokens(SECRET), str(certificate[0])
    view = ["view", "--server", served, "--room", "lobby", "--cafile", cafile, "--headless",
            "--out", str(tmp_path / "png"), "--size", "160x120", "--fps", "10"]
    expired = tokens.mint("lobby", "spectator", 60, now=time.time() - 3600)
    assert "the join token expired at" in _refusal_line(
        posecast(*view, "--token", expired, cwd=tmp_path))
    assert "the join token is for room 'attic', not 'lobby'" in _refusal_line(
        posecast(*view, "--token", tokens.mint("attic", "spectator", 60), cwd=tmp_path))
    play = subprocess.Popen([sys.executable, "-m", "posecast.client.cli", "play", "--server",
                             served, "--room", "lobby", "--source", CLIP, "--loop",
                             "--cafile", cafile, "--token",
                             tokens.mint("lobby", "player", 600)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            cwd=tmp_path)
    try:
        proc = posecast(*view, "--frames", "3", "--token",
                        tokens.mint("lobby", "spectator", 600), cwd=tmp_path)
    finally:
        play.terminate()
        _, play_err = play.communicate(timeout=WAIT)
    assert proc.returncode == 0, proc.stderr
    assert f"wrote 3 frames to {tmp_path / 'png'}" in proc.stdout, proc.stdout
    assert "1 player in room 'lobby'" in proc.stderr
    assert "joined room 'lobby'" in play_err


@pytest.mark.parametrize(("args", "words"), [
    (["--secret-file", "{missing}"], "--secret-file: no such secret file"),
    (["--secret-file", "{short}"], "--secret-file: the secret in"),
    (["--secret-file", "{secret}", "--ttl", "2 hours"], "--ttl must be a duration"),
    (["--secret-file", "{secret}", "--ttl", "0"], "--ttl must be above 0"),
    (["--secret-file", "{secret}", "--role", "admin"], "--role: invalid choice: 'admin'"),
    ([], "needs the server's secret: --secret-file FILE, or $POSECAST_SECRET"),
])
def test_bad_token_invocations_are_one_line_and_exit_2(
        args: list[str], words: str, secret_file: Path, tmp_path: Path,
        capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(SECRET_ENV, raising=False)
    short = tmp_path / "short"
    short.write_text("too short\n")
    files = {"{missing}": str(tmp_path / "nope"), "{short}": str(short),
             "{secret}": str(secret_file)}
    argv = ["token", "--room", "lobby", "--role", "player"]
    argv += [files.get(a, a) for a in args]
    if "--role" in args:
        argv[3:5] = []
    try:
        code = main(argv)
    except SystemExit as exit_info:
        code = exit_info.code  # type: ignore[assignment]
    assert code == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    (line,) = captured.err.splitlines()
    assert line.startswith("posecast token: ") and words in line, line


def test_the_real_token_command_has_no_traceback_for_a_short_secret(tmp_path: Path) -> None:
    (tmp_path / "short").write_text("1234\n")
    proc = posecast("token", "--secret-file", str(tmp_path / "short"), "--room", "lobby",
                    "--role", "player")
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.count("\n") == 1 and "is 4 bytes; use 32 or more" in proc.stderr
    proc = posecast("serve", "--port", "0", env={SECRET_ENV: "1234"})
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert f"{SECRET_ENV} is 4 bytes" in proc.stderr
