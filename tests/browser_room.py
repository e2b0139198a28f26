"""A real posecast server on 127.0.0.1 with players replaying the built-in walk, in a
process of its own, for tests that drive a browser (playwright's sync API) while the
room streams."""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing as mp
import shutil
import urllib.request
from multiprocessing.connection import Connection
from pathlib import Path

import pytest
from conftest import serving
from prometheus_client.parser import text_string_to_metric_families

from posecast.client.builtin import builtin_motion_path
from posecast.client.demo import HEADSET_HZ
from posecast.client.player import Ticker, run_player
from posecast.client.sources.bvh_source import BvhSource
from posecast.server.app import Session

START_TIMEOUT = 60.0  # a loaded machine starts a server and its players slowly
CHROMIUM = Path("/usr/bin/chromium")
# the closed network makes Chromium hang on its background requests without these
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                 "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync",
                 # WebGL on the CPU (SwiftShader), which newer builds want asked for
                 "--enable-unsafe-swiftshader"]


def chromium_or_skip() -> str:
    """Chromium's path, or a skip that says how to get it."""
    path = shutil.which("chromium") or (str(CHROMIUM) if CHROMIUM.exists() else None)
    if path is None:
        pytest.skip("no chromium on this machine: the browser tests need Debian's "
                    "(apt-get install chromium; make test installs it)")
    pytest.importorskip("playwright", reason="the browser tests drive Chromium with "
                        "playwright (pip install -e '.[dev]')")
    return path


class LiveRoom:
    """``players`` players walking side by side in ``room`` of a server in a process of
    its own (as ``posecast serve`` runs: the browser and the test do not share its
    core's time), until ``close``. The test sees it as a browser would: over HTTP."""

    def __init__(self, room: str = "lab", players: int = 2) -> None:
        self.room, self.players = room, players
        self.url = ""
        context = mp.get_context("spawn")  # no copy of the test process' threads
        self._pipe, child = context.Pipe()
        self._process = context.Process(target=_serve, args=(child, room, players),
                                        name="live-room", daemon=True)

    def __enter__(self) -> LiveRoom:
        self._process.start()
        if not self._pipe.poll(START_TIMEOUT):
            self._process.kill()
            raise RuntimeError(f"the test server did not start in {START_TIMEOUT:g} s")
        started = self._pipe.recv()
        if not started.startswith("ws://"):
            raise RuntimeError(f"the test server did not start: {started}")
        self.url = started
        return self

    def __exit__(self, *exc: object) -> None:
        with contextlib.suppress(OSError):
            self._pipe.send("stop")
        self._process.join(START_TIMEOUT)
        if self._process.is_alive():
            self._process.kill()

    @property
    def http(self) -> str:
        return "http" + self.url.removeprefix("ws")

    def metrics(self) -> dict[str, dict[tuple[tuple[str, str], ...], float]]:
        """/metrics as {sample name: {labels: value}} (made at most once a second)."""
        with urllib.request.urlopen(f"{self.http}/metrics", timeout=START_TIMEOUT) as reply:
            text = reply.read().decode()
        out: dict[str, dict[tuple[tuple[str, str], ...], float]] = {}
        for family in text_string_to_metric_families(text):
            for s in family.samples:
                out.setdefault(s.name, {})[tuple(sorted(s.labels.items()))] = s.value
        return out


def _serve(pipe: Connection, room: str, players: int) -> None:
    try:
        asyncio.run(_room(pipe, room, players))
    except BaseException as exc:  # said to the test, which raises it
        with contextlib.suppress(OSError):
            pipe.send(f"{type(exc).__name__}: {exc}")
        raise


async def _room(pipe: Connection, room: str, players: int) -> None:
    stop = asyncio.Event()
    sources = [BvhSource(builtin_motion_path(), loop=True, rate_hz=HEADSET_HZ,
                         offset=(1.2 * i - 0.6 * (players - 1), 0.0), start_frame=37 * i,
                         smooth=True)
               for i in range(players)]
    ticker = Ticker(HEADSET_HZ)
    try:
        async with serving(Session(reconnect_grace=0.0)) as url:
            pipe.send(url)
            told = asyncio.create_task(asyncio.to_thread(pipe.recv))
            told.add_done_callback(lambda _: stop.set())
            await asyncio.gather(*(
                run_player(url, room, f"player {i + 1}", source, ticker=ticker, stop=stop)
                for i, source in enumerate(sources)))
    finally:
        for source in sources:
            source.close()
