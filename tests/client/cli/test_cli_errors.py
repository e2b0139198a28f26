"""The CLI as a person meets it: a bad value is one line naming the option (exit 2), an
unreachable or refusing server one line (exit 1), never a traceback; play and view say
where they joined and whom they wait for, and Ctrl-C ends them with their summary and
status 130. The runtime cases run the real command in a subprocess against a real
server on 127.0.0.1."""

from __future__ import annotations

import argparse
import asyncio
import logging
import re
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Coroutine, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from commands import CLIP, WAIT, Command, closed_port, status_lines
from websockets.asyncio.client import connect
from websockets.asyncio.server import ServerConnection, serve

import posecast
from posecast.client.cli import _parser, arguments, main
from posecast.protocol import Error, encode
from posecast.protocol.validation import ROOM_NAME_RULE
from posecast.server.app import Session
from posecast.server.peers import safe_name
from posecast.server.serving import run_server

URL = "ws://127.0.0.1:8765"

# (argv, the option the one line must name); "{file}" is an existing plain file
BAD_ARGUMENTS: list[tuple[list[str], str]] = [
    (["play", "--server", URL, "--room", ""], "--room"),
    (["play", "--server", URL, "--room", "two words"], "--room"),
    (["play", "--server", URL, "--room", "x" * 65], "--room"),
    (["play", "--server", "ws://host:99999", "--room", "r"], "--server"),
    (["play", "--server", "localhost:8765", "--room", "r"], "--server"),
    (["play", "--server", "http://host:8765", "--room", "r"], "--server"),
    (["play", "--server", "ws://:8765", "--room", "r"], "--server"),
    (["view", "--server", "ws://host:0", "--room", "r"], "--server"),
    (["play", "--server", URL, "--room", "r", "--name", ""], "--name"),
    (["play", "--server", URL, "--room", "r", "--source", "vive:/no/such.csv"], "--source"),
    (["play", "--server", URL, "--room", "r", "--source", "kinect"], "--source"),
    (["play", "--server", URL, "--room", "r", "--devices", "/no/such.toml"], "--devices"),
    (["play", "--server", URL, "--room", "r", "--roles", "/no/such.toml"], "--roles"),
    (["play", "--server", URL, "--room", "r", "--devices", "head,hip"], "--devices"),
    (["play", "--server", URL, "--room", "r", "--dropouts", "often"], "--dropouts"),
    (["eval", "--devices", "5"], "--devices"),
    (["eval", "--dropouts", "6,max=0"], "--dropouts"),
    (["demo", "--devices", "head,elbow"], "--devices"),
    (["bench", "solver", "--devices", "2"], "--devices"),
    (["play", "--server", URL, "--room", "r", "--offset", "1"], "--offset"),
    (["play", "--server", URL, "--room", "r", "--offset", "1,nan"], "--offset"),
    (["play", "--server", URL, "--room", "r", "--seconds", "0"], "--seconds"),
    (["play", "--server", URL, "--room", "r", "--calibrate-in", "-1"], "--calibrate-in"),
    (["eval", "--smoothing", "1.5"], "--smoothing"),
    (["eval", "--smoothing", "-0.5"], "--smoothing"),
    (["eval", "--smoothing", "1"], "--smoothing"),
    (["eval", "/no/such/recording.csv"], "FILE"),
    (["view", "--server", URL, "--room", "r", "--fps", "0"], "--fps"),
    (["view", "--server", URL, "--room", "r", "--fps", "inf"], "--fps"),
    (["view", "--server", URL, "--room", "r", "--frames", "0"], "--frames"),
    (["view", "--server", URL, "--room", "r", "--frames", "-5"], "--frames"),
    (["view", "--server", URL, "--room", "r", "--out", "{file}"], "--out"),
    (["view", "--server", URL, "--room", "r", "--size", "10x10"], "--size"),
    (["view", "--server", URL, "--room", "r", "--max-rate", "0"], "--max-rate"),
    (["bench", "render", "--frames", "0"], "--frames"),
    (["bench", "render", "--size", "wide"], "--size"),
    (["bench", "solver", "--seconds", "-1"], "--seconds"),
    (["serve", "--port", "99999"], "--port"),
    (["serve", "--port", "-1"], "--port"),
    (["demo", "--players", "-1"], "--players"),
    (["demo", "--seconds", "0"], "--seconds"),
    (["--log-level", "loud", "eval"], "--log-level"),
    (["record", "--server", URL, "--room", "r", "--out", "{file}"], "--out"),
    (["record", "--server", URL, "--room", "r", "--out", "/no/such/dir/r.pcrec"], "--out"),
    (["record", "--server", URL, "--room", "r", "--out", "x.pcrec", "--seconds", "0"],
     "--seconds"),
    (["replay", "/no/such.pcrec", "--server", URL, "--room", "r"], "FILE"),
    (["replay", "{file}", "--server", URL, "--room", "r", "--speed", "0"], "--speed"),
    (["export", "{file}", "--bvh", "{file}"], "--bvh"),
    (["export", "{file}", "--bvh", "out", "--fps", "-30"], "--fps"),
    (["play", "--server", URL, "--room", "r", "--record", "{file}"], "--record"),
    (["vmc", "--server", URL, "--room", "r", "--to", "bad host:1"], "--to"),
    (["vmc", "--server", URL, "--room", "r", "--to", "host:70000"], "--to"),
    (["vmc", "--server", URL, "--room", "r", "--rate", "0"], "--rate"),
    (["vmc", "--server", URL, "--room", "r", "--avatar", ""], "--avatar"),
]


def _argv(argv: list[str], tmp_path: Path) -> list[str]:
    plain = tmp_path / "a_file.png"
    plain.write_bytes(b"not a folder")
    return [a.replace("{file}", str(plain)) for a in argv]


def _one_line(err: str, command: str, option: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith(f"posecast {command}: ") or lines[0].startswith("posecast: "), err
    assert option in lines[0], err
    return lines[0]


@pytest.mark.parametrize(("argv", "option"), BAD_ARGUMENTS,
                         ids=[" ".join(a)[:60] for a, _ in BAD_ARGUMENTS])
def test_a_bad_value_is_one_line_naming_the_option(argv: list[str], option: str,
                                                   tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(_argv(argv, tmp_path))
    assert exit_info.value.code == 2
    captured = capsys.readouterr()
    command = " ".join(a for a in argv[:2] if not a.startswith("-") and a in (
        "play", "view", "eval", "serve", "demo", "bench", "render", "solver", "record",
        "replay", "export", "vmc"))
    _one_line(captured.err, command, option)
    assert captured.out == ""


def test_the_room_rule_is_said_in_words(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["play", "--server", URL, "--room", ""])
    line = capsys.readouterr().err
    assert ROOM_NAME_RULE in line and "[A-Za-z" not in line


@pytest.mark.parametrize(("argv", "option"), [
    (["play", "--server", URL, "--room", ""], "--room"),
    (["play", "--server", "ws://host:99999", "--room", "r"], "--server"),
    (["eval", "--smoothing", "1.5"], "--smoothing"),
    (["view", "--server", URL, "--room", "r", "--fps", "0"], "--fps"),
    (["view", "--server", URL, "--room", "r", "--out", "{file}"], "--out"),
    (["bench", "render", "--frames", "0"], "--frames"),
    (["serve", "--port", "99999"], "--port"),
])
def test_the_real_command_never_shows_a_traceback(argv: list[str], option: str,
                                                  tmp_path: Path) -> None:
    proc = subprocess.run([sys.executable, "-m", "posecast.client.cli",
                           *_argv(argv, tmp_path)],
                          capture_output=True, text=True, timeout=WAIT, cwd=tmp_path)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr + proc.stdout
    _one_line(proc.stderr, " ".join(a for a in argv[:2] if not a.startswith("-")
                                    and a in ("play", "view", "eval", "serve", "bench",
                                              "render")), option)


# --------------------------------------------------------------------------- help
def test_bare_posecast_prints_help_and_exits_0(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([]) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: posecast") and "play" in out and "view" in out
    assert main(["bench"]) == 0
    assert "solver" in capsys.readouterr().out


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.strip() == f"posecast {posecast.__version__}"


def _every_parser() -> Iterator[argparse.ArgumentParser]:
    parser = _parser()
    yield parser
    yield from arguments.subparsers(parser)


def test_every_option_has_help_and_shows_its_default() -> None:
    for parser in _every_parser():
        text = parser.format_help()
        assert "default: None" not in text and "default: False" not in text, parser.prog
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction | argparse._HelpAction):
                continue
            assert action.help, f"{parser.prog} {action.option_strings or action.dest}"
            default = action.default
            if (action.option_strings and default not in (None, argparse.SUPPRESS)
                    and not isinstance(default, bool)):
                assert "default" in arguments.Formatter(parser.prog)._get_help_string(
                    action), f"{parser.prog} {action.option_strings}"


def test_log_level_goes_before_or_after_the_command(capsys: pytest.CaptureFixture[str]
                                                    ) -> None:
    for argv in (["--log-level", "debug", "serve", "--port", "1"],
                 ["serve", "--port", "1", "--log-level", "debug"]):
        assert _parser().parse_args(argv).log_level == "debug"
    assert _parser().parse_args(["serve"]).log_level is None


# --------------------------------------------------------------------------- servers
def _in_thread(make: Callable[[asyncio.Event, Callable[[int], None]],
                              Coroutine[Any, Any, object]]) -> Iterator[str]:
    """Run a server coroutine on its own loop in a thread; yield its URL, stop it after."""
    loop = asyncio.new_event_loop()
    ready = threading.Event()
    port: list[int] = []
    stop: list[asyncio.Event] = []

    def listening(number: int) -> None:
        port.append(number)
        ready.set()

    async def main() -> None:
        stop.append(asyncio.Event())
        await make(stop[0], listening)

    thread = threading.Thread(target=loop.run_until_complete, args=(main(),), daemon=True)
    thread.start()
    assert ready.wait(WAIT), "the test server did not start"
    try:
        yield f"ws://127.0.0.1:{port[0]}"
    finally:
        loop.call_soon_threadsafe(stop[0].set)
        thread.join(30)
        loop.close()


@pytest.fixture(scope="module")
def server() -> Iterator[str]:
    """A real posecast server on 127.0.0.1, in a thread of this process (its log lines
    reach caplog)."""
    session = Session(reconnect_grace=0.0)

    def make(stop: asyncio.Event, ready: Callable[[int], None]
             ) -> Coroutine[Any, Any, object]:
        return run_server("127.0.0.1", 0, session, stop, ready)

    yield from _in_thread(make)


@contextmanager
def refusing_server(reason: str) -> Iterator[str]:
    """A websocket server that answers every hello with an Error, as a server with
    rules of its own (a closed room, a full one) would."""
    async def refuse(ws: ServerConnection) -> None:
        await ws.recv()
        await ws.send(encode(Error(code="not_allowed", message=reason)))
        await ws.close(1008, "not_allowed")

    async def make(stop: asyncio.Event, ready: Callable[[int], None]) -> None:
        async with serve(refuse, "127.0.0.1", 0) as running:
            ready(next(iter(running.sockets)).getsockname()[1])
            await stop.wait()

    yield from _in_thread(make)


@pytest.mark.parametrize("command", ["play", "view", "record", "vmc"])
def test_an_unreachable_server_is_one_line(command: str, tmp_path: Path) -> None:
    url = f"ws://127.0.0.1:{closed_port()}"
    extra = {"play": ["--source", CLIP], "record": ["--out", str(tmp_path / "r.pcrec")],
             "view": ["--headless", "--out", str(tmp_path / "png")], "vmc": []}[command]
    code, out, err = Command(command, "--server", url, "--room", "r", *extra,
                             cwd=tmp_path).finish()
    assert code == 1 and "Traceback" not in err + out
    (line,) = status_lines(err)
    assert line.startswith(f"posecast {command}: cannot reach {url}: connection refused"), err


def test_a_refused_join_is_one_line_with_the_servers_reason(tmp_path: Path) -> None:
    reason = "this room is closed for the night"
    with refusing_server(reason) as url:
        code, out, err = Command("play", "--server", url, "--room", "r", "--source", CLIP,
                                 cwd=tmp_path).finish()
    assert code == 1 and "Traceback" not in err + out
    (line,) = status_lines(err)
    assert line.startswith(f"posecast play: {url}: ") and reason in line, err


def test_the_real_server_states_the_room_rule_in_words(server: str,
                                                       caplog: pytest.LogCaptureFixture
                                                       ) -> None:
    import msgpack

    from posecast.protocol import PROTOCOL_VERSION, decode

    caplog.set_level(logging.INFO, logger="posecast.server")

    async def hello_with_bad_room() -> object:
        async with connect(server, compression=None) as ws:
            await ws.send(msgpack.packb({"type": "hello", "protocol_version": PROTOCOL_VERSION,
                                         "role": "player", "room": "no\nroom",
                                         "display_name": "x"}))
            return decode(await asyncio.wait_for(ws.recv(), WAIT))

    reply = asyncio.run(hello_with_bad_room())
    assert isinstance(reply, Error) and ROOM_NAME_RULE in reply.message
    (line,) = [r.getMessage() for r in caplog.records if "refused a connection" in r.getMessage()]
    assert re.search(r"from 127\.0\.0\.1:\d+: ", line) and "\n" not in line


# --------------------------------------------------------------------------- running
def test_play_says_where_it_joined_and_stops_on_ctrl_c(server: str, tmp_path: Path,
                                                       caplog: pytest.LogCaptureFixture
                                                       ) -> None:
    caplog.set_level(logging.INFO, logger="posecast.server")
    play = Command("play", "--server", server, "--room", "sigplay", "--name", "ann",
                   "--source", CLIP, "--loop", cwd=tmp_path)
    joined = play.wait_for("joined room")
    assert "'sigplay'" in joined and server in joined and "'ann'" in joined
    assert re.search(r"\(avatar \d+\)", joined) and CLIP in joined
    play.wait_for(" frames/s")  # the progress line: frames are going out
    code, out, err = play.interrupt()
    assert code == 130 and "Traceback" not in err + out
    summary = re.fullmatch(r"sent (\d+) frames in ([\d.]+) s \(([\d.]+) frames/s\) from "
                           r"10 devices \(head, [a-z_, ]+\); no device lost\n", out)
    assert summary is not None and int(summary[1]) > 0, out

    # the server's log names role, name, room and address on join and on leave
    def server_lines() -> list[str]:
        return [r.getMessage() for r in caplog.records if "'sigplay'" in r.getMessage()]
    deadline = time.monotonic() + WAIT
    while not any("left" in line for line in server_lines()) and time.monotonic() < deadline:
        time.sleep(0.1)
    join, leave = server_lines()
    for line in (join, leave):
        assert re.match(r"player 'ann' in room 'sigplay' from 127\.0\.0\.1:\d+ ", line), line
    assert "joined" in join and "left" in leave


def test_view_of_an_empty_room_says_it_waits_and_stops_on_ctrl_c(server: str, egl: None,
                                                                  tmp_path: Path) -> None:
    out_dir = tmp_path / "png"
    view = Command("view", "--headless", "--server", server, "--room", "nobody-here",
                   "--out", str(out_dir), "--size", "160x120", "--fps", "5", cwd=tmp_path)
    waiting = view.wait_for("waiting for players")
    assert "'nobody-here'" in waiting and server in waiting
    code, out, err = view.interrupt()
    assert code == 130 and "Traceback" not in err + out
    assert out.startswith("received 0 avatar-frames in ")
    assert f"wrote no frames to {out_dir}" in out
    assert err.count("waiting for players") >= 1


def test_view_says_what_it_wrote_where(server: str, egl: None, tmp_path: Path) -> None:
    out_dir = tmp_path / "png"
    play = Command("play", "--server", server, "--room", "watched", "--source", CLIP,
                   "--loop", cwd=tmp_path)
    view = Command("view", "--headless", "--server", server, "--room", "watched",
                   "--out", str(out_dir), "--size", "160x120", "--fps", "10",
                   "--frames", "100000", cwd=tmp_path)
    try:
        view.wait_for("1 player in room 'watched'")
        deadline = time.monotonic() + WAIT
        while not list(out_dir.glob("*.png")) and time.monotonic() < deadline:
            time.sleep(0.1)
        code, out, err = view.interrupt()
    finally:
        play_code, _, play_err = play.interrupt()
    assert code == 130 and "Traceback" not in err + out
    written = re.search(r"^wrote (\d+) frames to (.+)$", out, re.MULTILINE)
    assert written is not None and written[2] == str(out_dir), out
    assert int(written[1]) == len(list(out_dir.glob("*.png"))) > 0
    # people's figures: latencies with two decimals, never a 15-digit float
    assert re.search(r"capture_to_render: p50 \d+\.\d\d ms, p99 \d+\.\d\d ms", out), out
    assert not re.search(r"\d\.\d{5,}", out), out
    assert play_code == 130 and "Traceback" not in play_err


def test_log_lines_never_carry_raw_client_text() -> None:
    line = safe_name("evil\n2026-01-01 INFO forged line\x1b[31m" + "x" * 100)
    assert "\n" not in line and "\x1b" not in line and len(line) < 60


def test_play_with_three_devices_losing_some_streams_on_and_counts_them(
        server: str, tmp_path: Path) -> None:
    """`play --devices 4 --dropouts ...`: head, hands and hip, some lost now and then:
    never an error from the server, and the summary names what was lost."""
    play = Command("play", "--server", server, "--room", "sets", "--source", CLIP,
                   "--loop", "--devices", "4", "--dropouts", "120,max=0.5,seed=2",
                   "--seconds", "3", cwd=tmp_path)
    code, out, err = play.finish()
    assert code == 0, err
    assert "from 4 devices (head, hip, left_hand, right_hand)" in out, out
    assert "; lost: " in out and "server errors" not in out + err, out + err
