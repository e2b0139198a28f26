"""Clients come back by themselves (issue 15): a player resumes its avatar, still
calibrated, after a drop; after a server restart it gets a new avatar and calibrates
again; a viewer rejoins its room. Real servers on 127.0.0.1, stopped and started again
on the same port, and the real CLI against a `posecast serve` killed with SIGKILL."""

from __future__ import annotations

import asyncio
import contextlib
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from posecast.client.bench.redis_process import free_port
from posecast.client.builtin import builtin_motion_path
from posecast.client.session.connection import Reconnect, SessionError
from posecast.client.session.player import Player
from posecast.client.session.spectator import Spectator
from posecast.client.sources import open_source
from posecast.server.app import Session
from posecast.server.serving import run_server

TIMEOUT = 60.0  # generous: conditions are awaited, and a loaded machine starts processes slowly
QUICK = {"first_s": 0.05, "max_s": 0.2}  # backoff for tests: the figures, not the waits


class Restartable:
    """A real server on a fixed port of 127.0.0.1 that a test stops and starts again."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.url = f"ws://127.0.0.1:{port}"
        self.session: Session | None = None
        self._stop: asyncio.Event | None = None
        self._task: asyncio.Task[Session] | None = None

    async def start(self, reconnect_grace: float = 30.0) -> Session:
        self.session = Session(reconnect_grace=reconnect_grace)
        self._stop = asyncio.Event()
        ready: asyncio.Future[int] = asyncio.get_running_loop().create_future()
        self._task = asyncio.create_task(run_server("127.0.0.1", self.port, self.session,
                                                    self._stop, ready.set_result))
        await asyncio.wait_for(ready, TIMEOUT)
        return self.session

    async def stop(self) -> None:
        assert self._stop is not None and self._task is not None
        self._stop.set()
        await asyncio.wait_for(self._task, TIMEOUT)


async def until(condition: object, what: str) -> None:
    t_end = time.monotonic() + TIMEOUT
    while not condition():  # type: ignore[operator]
        assert time.monotonic() < t_end, f"timed out waiting for {what}"
        await asyncio.sleep(0.02)


def test_after_a_restart_a_player_calibrates_again_and_a_viewer_rejoins() -> None:
    said: list[str] = []

    async def main() -> None:
        server = Restartable(free_port())
        await server.start()
        source = open_source(f"bvh:{builtin_motion_path()}", loop=True)
        player = Player(server.url, "again", "pat", source,
                        reconnect=Reconnect(say=said.append, **QUICK))
        viewer = Spectator(server.url, "again", "viewer",
                           reconnect=Reconnect(say=said.append, **QUICK))
        stop = asyncio.Event()
        tasks = [asyncio.create_task(player.run(stop=stop)),
                 asyncio.create_task(viewer.run(stop=stop))]
        try:
            await until(lambda: viewer.stats.frames_received > 20, "frames before")
            await server.stop()  # every connection closed with 1001
            t_down = time.monotonic()
            await asyncio.sleep(0.5)  # down for a while: the clients keep trying
            session = await server.start()
            await until(lambda: session.metrics.frames_solved > 20, "frames after")
            await until(lambda: len(viewer.latest) == 1, "the viewer to see the player")
            back_in = time.monotonic() - t_down
            print(f"streaming again {back_in:.2f} s after the server went down")
        finally:
            stop.set()
            await asyncio.wait_for(asyncio.gather(*tasks), TIMEOUT)
            source.close()
        assert player.stats.reconnects == 1 and viewer.stats.reconnects == 1
        assert player.stats.calibrations_sent == 2  # the new server had no avatar for it
        assert player.stats.avatar_id in viewer.latest
        assert set(viewer.roster) == set(viewer.latest)  # the old server's avatar is gone
        await server.stop()

    asyncio.run(main())
    assert sum("connection lost" in line for line in said) == 2, said
    assert any("a new avatar" in line and "calibrating again" in line for line in said)
    assert any(f"back in room {'again'!r}" in line for line in said), said


def test_after_a_drop_a_player_resumes_its_avatar_calibrated() -> None:
    said: list[str] = []

    async def main() -> None:
        server = Restartable(free_port())
        session = await server.start()
        source = open_source(f"bvh:{builtin_motion_path()}", loop=True)
        player = Player(server.url, "drop", "pat", source,
                        reconnect=Reconnect(say=said.append, **QUICK))
        stop = asyncio.Event()
        task = asyncio.create_task(player.run(stop=stop))
        try:
            await until(lambda: session.metrics.frames_solved > 20, "frames")
            first = player.stats.avatar_id
            room = session.rooms["drop"]
            ws = player.session.ws if player.session is not None else None
            assert ws is not None
            own = next(c for c in session._owners.values()
                       if c.remote_address[1] == ws.local_address[1])
            own.transport.abort()  # the network drops it: no close on either side
            solved = session.metrics.frames_solved
            await until(lambda: player.stats.reconnects == 1, "the reconnect")
            await until(lambda: session.metrics.frames_solved > solved + 20, "frames again")
            assert list(room.avatars) == [first]  # the one avatar, streaming again
        finally:
            stop.set()
            await asyncio.wait_for(task, TIMEOUT)
            source.close()
        assert player.stats.avatar_id == first
        assert player.stats.calibrations_sent == 1  # resumed: no second T-pose
        await server.stop()

    asyncio.run(main())
    assert any("avatar resumed, still calibrated" in line for line in said), said


def test_no_reconnect_after_a_policy_close_or_without_a_policy() -> None:
    """A server that closes us for cause (1008) or a client without a Reconnect: the
    session ends with its one-line reason; nothing loops against the server."""
    async def main() -> None:
        server = Restartable(free_port())
        session = await server.start()
        viewer = Spectator(server.url, "policy", "viewer",
                           reconnect=Reconnect(say=lambda _: None, **QUICK))
        task = asyncio.create_task(viewer.run())
        await until(lambda: viewer.session is not None, "the viewer")
        spectator_ws = next(s.connection for r in session.rooms.values()
                            for s in r.spectators.values())
        assert spectator_ws is not None
        await spectator_ws.close(1008, "told to go")
        with pytest.raises(SessionError, match="1008"):
            await asyncio.wait_for(task, TIMEOUT)
        assert viewer.stats.reconnects == 0

        plain = Spectator(server.url, "policy", "plain")  # no policy: a drop ends it
        task = asyncio.create_task(plain.run())
        await until(lambda: plain.session is not None, "the plain viewer")
        await server.stop()
        with pytest.raises(SessionError, match="1001"):
            await asyncio.wait_for(task, TIMEOUT)

    asyncio.run(main())


# ---------------------------------------------------------------------- the real CLI
class Command:
    """A posecast command in a subprocess whose stderr lines are collected as they come."""

    def __init__(self, *args: str) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", "posecast.client.cli", *args],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.lines.append(line.rstrip("\n"))

    def said(self, words: str, after: str | None = None) -> bool:
        """Whether a line has ``words`` (after the first line that has ``after``)."""
        lines = list(self.lines)
        if after is not None:
            first = next((i for i, line in enumerate(lines) if after in line), None)
            if first is None:
                return False
            lines = lines[first + 1:]
        return any(words in line for line in lines)

    def stop(self) -> str:
        """SIGINT, wait, and its whole stderr."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        self.proc.communicate(timeout=TIMEOUT)
        self._reader.join(TIMEOUT)
        return "\n".join(self.lines)


@contextlib.contextmanager
def serve(port: int) -> Iterator[Command]:
    server = Command("serve", "--port", str(port), "--log-level", "warning")
    try:
        t_end = time.monotonic() + TIMEOUT
        while True:  # listening: a TCP connect succeeds
            with contextlib.suppress(OSError), socket.create_connection(
                    ("127.0.0.1", port), timeout=1.0):
                break
            assert server.proc.poll() is None, server.lines
            assert time.monotonic() < t_end, "serve did not listen"
            time.sleep(0.05)
        yield server
    finally:
        if server.proc.poll() is None:
            server.proc.kill()
        server.proc.communicate()


def wait_for(condition: Callable[[], bool], what: str, *commands: Command) -> None:
    t_end = time.monotonic() + TIMEOUT
    while not condition():
        assert time.monotonic() < t_end, f"timed out waiting for {what}: " + " | ".join(
            "; ".join(c.lines) for c in commands)
        assert all(c.proc.poll() is None for c in commands), [c.lines for c in commands]
        time.sleep(0.05)


def test_play_and_view_come_back_after_the_server_is_killed_and_restarted(
        tmp_path: Path) -> None:
    port = free_port()
    url = f"ws://127.0.0.1:{port}"
    with serve(port) as first:
        play = Command("play", "--server", url, "--room", "kill", "--source",
                       f"bvh:{builtin_motion_path()}", "--loop", "--seconds", "60")
        view = Command("view", "--server", url, "--room", "kill", "--headless",
                       "--frames", "100000", "--fps", "5", "--out", str(tmp_path))
        try:
            wait_for(lambda: view.said("1 player in room"), "the viewer to see the player",
                     play, view)
            first.proc.send_signal(signal.SIGKILL)
            first.proc.wait()
            t_killed = time.monotonic()
            time.sleep(1.0)
            with serve(port):
                try:
                    wait_for(lambda: play.said("reconnected after")
                             and view.said("1 player in room", after="reconnected after"),
                             "both back, the viewer showing the player", play, view)
                    print(f"back {time.monotonic() - t_killed:.1f} s after the kill")
                finally:  # while this server runs: their goodbye is no lost connection
                    errs = [play.stop(), view.stop()]
        finally:
            for command in (play, view):
                if command.proc.poll() is None:
                    command.proc.kill()
    for err, name in zip(errs, ("play", "view"), strict=True):
        lost = [line for line in err.splitlines() if "connection lost" in line]
        back = [line for line in err.splitlines() if "reconnected after" in line]
        assert len(lost) == 1 and lost[0].startswith(f"posecast {name}: "), err
        assert len(back) == 1 and "Traceback" not in err, err
    assert "calibrating again" in errs[0]
