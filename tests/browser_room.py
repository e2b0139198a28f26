"""A real posecast server on 127.0.0.1 with players replaying the built-in walk (some
losing devices now and then, if asked), in a process of its own, for tests that drive a
browser (playwright's sync API) while the room streams."""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing as mp
import urllib.request
from multiprocessing.connection import Connection

import pytest
from conftest import serving
from prometheus_client.parser import text_string_to_metric_families

from posecast.client.bench.browser import BrowserMissingError, find_chromium
from posecast.client.bench.demo import HEADSET_HZ
from posecast.client.builtin import builtin_motion_path
from posecast.client.session.player import Ticker, run_player
from posecast.client.sources.base import DeviceSample, PoseSource
from posecast.client.sources.bvh_source import BvhSource
from posecast.server.app import Session

START_TIMEOUT = 60.0  # a loaded machine starts a server and its players slowly
LOSS_FRAMES = 90  # a losing player's devices are lost this many frames (1 s), then found
def chromium_or_skip() -> str:
    """Chromium's path, or a skip that says how to get it (and playwright)."""
    try:
        return find_chromium()
    except BrowserMissingError as missing:
        pytest.skip(f"{missing} (make test installs both)")


class LosingSource:
    """``source`` whose frames lack ``roles`` for LOSS_FRAMES frames, then have them for
    as many, and so on (the T-pose has them all): a tracker hidden now and then."""

    def __init__(self, source: PoseSource, roles: tuple[str, ...]) -> None:
        self.source, self.roles = source, roles
        self.rate_hz = source.rate_hz
        self._frames = 0

    def calibration(self) -> DeviceSample:
        return self.source.calibration()

    def read(self) -> DeviceSample | None:
        sample = self.source.read()
        self._frames += 1
        if sample is None or (self._frames // LOSS_FRAMES) % 2:
            return sample
        keep = [i for i, r in enumerate(sample.roles) if r not in self.roles]
        return DeviceSample(sample.t_capture, tuple(sample.roles[i] for i in keep),
                            sample.poses[keep])

    def close(self) -> None:
        self.source.close()


class LiveRoom:
    """``players`` players walking side by side in ``room`` of a server in a process of
    its own (as ``posecast serve`` runs: the browser and the test do not share its
    core's time), until ``close``; player i + 1 loses ``lose[i]``'s devices now and then
    (LosingSource). The test sees it as a browser would: over HTTP."""

    def __init__(self, room: str = "lab", players: int = 2,
                 lose: dict[int, tuple[str, ...]] | None = None) -> None:
        self.room, self.players = room, players
        self.url = ""
        context = mp.get_context("spawn")  # no copy of the test process' threads
        self._pipe, child = context.Pipe()
        self._process = context.Process(target=_serve, args=(child, room, players, lose or {}),
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


def _serve(pipe: Connection, room: str, players: int,
           lose: dict[int, tuple[str, ...]]) -> None:
    try:
        asyncio.run(_room(pipe, room, players, lose))
    except BaseException as exc:  # said to the test, which raises it
        with contextlib.suppress(OSError):
            pipe.send(f"{type(exc).__name__}: {exc}")
        raise


async def _room(pipe: Connection, room: str, players: int,
                lose: dict[int, tuple[str, ...]]) -> None:
    stop = asyncio.Event()
    sources: list[PoseSource] = [
        BvhSource(builtin_motion_path(), loop=True, rate_hz=HEADSET_HZ,
                  offset=(1.2 * i - 0.6 * (players - 1), 0.0), start_frame=37 * i, smooth=True)
        for i in range(players)]
    sources = [LosingSource(s, lose[i]) if i in lose else s for i, s in enumerate(sources)]
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
