"""`posecast demo`: a whole session on this machine, measured.

An embedded server runs in its own process (its event loop must not share a core's time
with the clients it serves, or its latency would measure theirs); N players replay the
built-in motion from one shared schedule, as headsets at the same rate would, and M
headless spectators receive. The result: frame counts and per-stage latency percentiles,
all on the server clock, and the display error of each viewer mode (``display_error``).
With a network spec, every connection goes through the emulator (``network``), both ways.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import itertools
import multiprocessing as mp
import os
import threading
from collections.abc import Callable, Coroutine, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import partial
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, TypeVar

from posecast.client.bench.browser import (
    BrowserSpectator,
    PageMeasure,
    find_chromium,
    measure_page,
)
from posecast.client.bench.network import NetworkSpec, ProxyProcess
from posecast.client.builtin import builtin_motion_path
from posecast.client.measure.display_error import (
    Arrival,
    CaptureLog,
    DisplayError,
    RecordingSource,
    clock_error_ms,
    measure_display_error,
)
from posecast.client.measure.latency import LatencyRecorder
from posecast.client.session.connection import SessionError
from posecast.client.session.player import PlayerStats, Ticker, run_player
from posecast.client.session.spectator import Spectator, SpectatorStats
from posecast.client.sources.base import PoseSource
from posecast.client.sources.bvh_source import BvhSource
from posecast.client.sources.tracker_set import TrackerSetSource
from posecast.client.viewer.headless import HeadlessViewerProcess
from posecast.client.viewer.interpolation import Mode
from posecast.protocol import AvatarBatch, AvatarRoster, ClockEstimator
from posecast.server.limits import ServerLimits
from posecast.solver.readers.gltf import load_makehuman
from posecast.solver.rig import Rig, build_rig
from posecast.solver.tracking.devices import DEFAULT_SET, parse_devices
from posecast.solver.tracking.dropouts import DropoutSpec

ROOM = "demo"
T = TypeVar("T")
# generous: on a loaded machine, joining (the server's own start included) and the
# server's stop (its drain, then every close handshake) may take seconds
JOIN_TIMEOUT = 60.0
STOP_TIMEOUT = 60.0
HEADSET_HZ = 90.0  # an HTC Vive's rate: players send what their headset samples
# players whose display error is measured: a few say it as well as many, and the work
# after the session (and the samples sent back) stays small however many play
MEASURED_PLAYERS = 4
# demo --servers: the owner stops first; the others this much later, once its last
# batches have crossed Redis (a hop takes well under a millisecond)
RELAY_SETTLE_S = 0.5


class DemoError(RuntimeError):
    """The session could not run to its end (a player refused or gone): one line."""


@dataclass
class DemoResult:
    players: int
    spectators: int
    seconds: float
    # tracker frames the players sent: each is exactly one of solved, superseded,
    # discarded, rejected, unsendable (the server's counts, read once it stopped)
    frames_sent: int
    frames_solved: int
    frames_delivered: int  # received, summed over the spectators
    frames_dropped: int  # offered to a spectator but never sent to it
    batches: int  # solves the server ran: frames_solved / batches = avatars per batch
    rejected: dict[str, int]
    latency: LatencyRecorder
    rendered: int = 0  # PNG frames the viewer wrote (with --render)
    frames_superseded: int = 0  # a newer frame of the same player came before its solve
    frames_discarded: int = 0  # unsolved: its player left first
    frames_rejected: int = 0  # refused by the server with an Error
    # solved, but its row would fail a spectator's checks: dropped from its batch alone
    frames_unsendable: int = 0
    viewer: bool = False  # --render: one more spectator, whose drops frames_dropped counts
    network: str = "loopback"  # the emulated link's spec (each direction), or loopback
    # spectator 1's presented pose vs the player's true one, per viewer mode (mm)
    display_error: DisplayError = field(default_factory=DisplayError)
    proxy: dict[str, object] = field(default_factory=dict)  # the emulator's counts
    servers: int = 1  # server processes sharing the room through Redis
    frames_relayed: int = 0  # avatar-frames the other processes got through Redis
    devices: list[str] = field(default_factory=list)  # each player's tracker set
    dropouts: str | None = None  # the simulated losses' spec
    # the server's counts, by role: tracker frames that lacked one of the avatar's
    # devices, and losses (carried on by the body model, never refused)
    device_lost_frames: dict[str, int] = field(default_factory=dict)
    device_losses: dict[str, int] = field(default_factory=dict)
    browser: PageMeasure | None = None  # --browser: what the page showed, measured
    # spectator 1's clock estimate minus the server's clock (one machine: the true offset
    # is 0), its median over the batches: what its prediction reckons with
    clock_error_ms: float | None = None
    # the server's own display error (its /metrics) of what viewers reported showing,
    # per "viewer/mode": p50/p95 read off its histogram's buckets, mm
    metrics_display_error: dict[str, dict[str, float]] = field(default_factory=dict)

    def as_json(self) -> dict[str, object]:
        return {"players": self.players, "spectators": self.spectators,
                "seconds": round(self.seconds, 3), "frames_sent": self.frames_sent,
                "frames_solved": self.frames_solved,
                "frames_delivered": self.frames_delivered,
                "frames_dropped": self.frames_dropped,
                "frames_superseded": self.frames_superseded,
                "frames_discarded": self.frames_discarded,
                "frames_rejected": self.frames_rejected,
                "frames_unsendable": self.frames_unsendable, "batches": self.batches,
                "rejected": self.rejected, "frames_rendered": self.rendered,
                "latency_ms": self.latency.summary(), "network": self.network,
                "display_error_mm": self.display_error.as_json(),
                "playout_delay_ms": self.display_error.delay_json(),
                # the emulator's chunks, bytes, stalls and median delay per direction
                "network_counts": self.proxy, "servers": self.servers,
                "frames_relayed": self.frames_relayed, "devices": self.devices,
                "dropouts": self.dropouts, "device_lost_frames": self.device_lost_frames,
                "device_losses": self.device_losses,
                "browser": self.browser.as_json() if self.browser is not None else None,
                "clock_error_ms": self.clock_error_ms,
                "metrics_display_error_mm": self.metrics_display_error}

    def format_display_error(self) -> str:
        """What a spectator sees, per viewer mode: p50/p95 of the display error."""
        lines = [f"display error over {self.network} (spectator 1's presented pose vs the "
                 "player's true pose at that instant, mm):"]
        for mode, e in self.display_error.as_json().items():
            if mode == "browser" and self.browser is not None:
                mode = f"browser ({self.browser.mode})"
            lines.append(f"  {mode:<21} p50 {e['p50']:7.1f}  p95 {e['p95']:7.1f}")
        if self.browser is not None:
            lines.append(f"  (the browser page in headless Chromium: {self.browser.describe()})")
            ms = [f"{e:+.1f} ms" if e is not None else "never synced"
                  for e in (self.browser.clock_error_ms, self.clock_error_ms)]
            lines.append(f"  clock estimates against the server's: the page's {ms[0]}, "
                         f"spectator 1's {ms[1]}")
        for key, e in self.metrics_display_error.items():
            lines.append(f"  /metrics, {key:<12} p50 {e['p50']:7.1f}  p95 {e['p95']:7.1f}  "
                         f"(the server's, of {e['n']:g} poses the viewer reported showing; "
                         "with the clip's seams, which the rows above leave out)")
        d = self.display_error.delay_json()
        lines.append(f"  interpolation's playout delay: p50 {d['p50']:.1f} ms, "
                     f"p95 {d['p95']:.1f} ms (grows with the jitter it measures)")
        return "\n".join(lines)

    def format_counts(self) -> str:
        """The counts for a reader: what each means, and whether the two identities the
        demo's test asserts hold."""
        rows = [("sent", self.frames_sent, "tracker frames the players sent"),
                ("solved", self.frames_solved, "solved by the server and sent"),
                ("superseded", self.frames_superseded, "a player's newer frame arrived "
                 "before the older one was solved; the newer one is solved"),
                ("discarded", self.frames_discarded, "not solved: its player left first"),
                ("rejected", self.frames_rejected, "refused by the server with an error"),
                ("unsendable", self.frames_unsendable, "solved, but a spectator would "
                 "refuse its row (e.g. a root beyond the world): dropped alone"),
                ("delivered", self.frames_delivered, "received, summed over the spectators"),
                ("dropped", self.frames_dropped, "not sent to a spectator: a newer frame of "
                 "the avatar replaced it in its outbox (latest wins)")]
        if self.servers > 1:
            rows.insert(2, ("relayed", self.frames_relayed, f"solved frames the other "
                            f"{self.servers - 1} processes got through Redis, for their "
                            f"spectators"))
        lost = sum(self.device_lost_frames.values())
        if lost or self.dropouts:
            rows.append(("lost", lost, "frames that lacked one of their avatar's devices "
                         "(counted once per device), solved with it carried on: not errors"))
        width = max(len(str(n)) for _, n, _ in rows)
        where = f" over {self.servers} server processes" if self.servers > 1 else ""
        sets = ""
        if self.devices:
            kinds = sorted(set(self.devices), key=self.devices.index)
            sets = ", tracker sets " + " / ".join(
                f"{k} x{self.devices.count(k)}" for k in kinds)
        lines = [f"{self.players} players{sets}, {self.spectators} spectators{where}, "
                 f"{self.seconds:g} s"
                 + (f", dropouts {self.dropouts}" if self.dropouts else "")
                 + "; avatar-frames:"]
        lines += [f"  {name:<10} {n:>{width}}  {what}" for name, n, what in rows]
        if self.device_losses:
            lines.append("  losses by device: " + ", ".join(
                f"{role} {n}" for role, n in sorted(self.device_losses.items())))
        gap = self.frames_sent - (self.frames_solved + self.frames_superseded
                                  + self.frames_discarded + self.frames_rejected
                                  + self.frames_unsendable)
        lines.append("  sent = solved + superseded + discarded + rejected + unsendable: "
                     + ("yes" if gap == 0 else f"no, {gap:+d}"))
        if self.viewer:  # its frames are not in delivered, its drops are in dropped
            lines.append("  (dropped includes the --render viewer's)")
        else:
            gap = self.frames_solved * self.spectators - (self.frames_delivered
                                                          + self.frames_dropped)
            lines.append(f"  solved x {self.spectators} spectators = delivered + dropped: "
                         + ("yes" if gap == 0 else f"no, {gap:+d}"))
        return "\n".join(lines)


Cores = tuple[int, ...]


def demo_cores() -> Cores:
    """The cores this demo may use: the caller's affinity when the demo starts. Each
    process is pinned from this set, passed to it, because a process spawned after its
    parent pinned itself would otherwise inherit (and split) the parent's share only."""
    return tuple(sorted(os.sched_getaffinity(0))) if hasattr(os, "sched_getaffinity") else ()


def pin_to_cores(role: str, cores: Cores) -> None:
    """Where each process of the demo runs, when there are at least two cores: the server
    alone on the first, players and spectators on the others.

    The server then reads each player's frame as it arrives, while the players are still
    sending the rest of the burst (as frames from separate machines would come in); on a
    core shared with the players it could only start when their whole burst was sent.
    Spectators decode every batch the moment the server writes it; on the server's core
    their wake-ups preempted it in the middle of its 16 writes
    (docs/decisions/0005-busy-polling-and-solver-helper.md).
    """
    if len(cores) < 2:
        return
    if role.startswith("core:"):  # one of many servers: "core:K", the K-th core (wrapping)
        os.sched_setaffinity(0, {cores[int(role[5:]) % len(cores)]})
        return
    os.sched_setaffinity(0, cores[:1] if role == "server" else cores[1:])


def _serve_process(pipe: Connection, solver: str, cores: Cores, busy: bool,
                   helper: bool | None, limits: ServerLimits | None = None,
                   redis_url: str | None = None, role: str = "server") -> None:
    """The server process: report the port, serve until told to stop, report metrics
    (and, one of many through Redis, the relay hops it measured)."""
    from posecast.server.app import Session
    from posecast.server.cluster import Cluster
    from posecast.server.serving import install_fast_loop, run_server

    pin_to_cores(role, cores)
    install_fast_loop()

    async def main() -> dict[str, object]:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        loop.add_reader(pipe.fileno(), stop.set)  # any message from the parent: stop
        cluster = Cluster(redis_url, "") if redis_url is not None else None
        session = Session(solver=solver, busy=busy, helper=helper, limits=limits,
                          cluster=cluster)
        await run_server("127.0.0.1", 0, session, stop, ready=pipe.send,
                         drain_timeout=STOP_TIMEOUT / 2)
        return {**session.metrics.as_json(),
                "relay_samples": session.metrics.relay_latency.samples}

    pipe.send(asyncio.run(main()))


class EmbeddedServer:
    """A server process on loopback for the length of a ``with`` block."""

    def __init__(self, solver: str = "analytic", cores: Cores = (),
                 busy: bool = False, helper: bool | None = None,
                 limits: ServerLimits | None = None, redis_url: str | None = None,
                 role: str = "server") -> None:
        """``redis_url``: one of many processes sharing rooms (``serve --redis``);
        ``role``: where it runs (``pin_to_cores``)."""
        ctx = mp.get_context("spawn")  # a fresh interpreter: no inherited event loop
        self._pipe, child = ctx.Pipe()
        self._process = ctx.Process(target=_serve_process,
                                    args=(child, solver, cores, busy, helper, limits,
                                          redis_url, role),
                                    daemon=True)
        self.port = 0
        self.metrics: dict[str, object] = {}
        self._stopped = False

    def __enter__(self) -> EmbeddedServer:
        self._process.start()
        if not self._pipe.poll(60):
            self._process.kill()
            raise RuntimeError("the embedded server did not start within 60 s")
        self.port = int(self._pipe.recv())
        return self

    @property
    def url(self) -> str:
        return f"ws://127.0.0.1:{self.port}"

    def stop(self) -> None:
        """Ask the server to stop: it solves what is pending, lets the spectators'
        outboxes empty, closes every connection, then reports its metrics."""
        if not self._stopped:
            self._stopped = True
            self._pipe.send("stop")

    def __exit__(self, *exc: object) -> None:
        self.stop()
        if self._pipe.poll(STOP_TIMEOUT):
            self.metrics = self._pipe.recv()
        self._process.join(10)
        if self._process.is_alive():
            self._process.kill()
        if not self.metrics and exc[0] is None:  # no counts: do not report zeros
            raise RuntimeError(f"the embedded server did not report its metrics within "
                               f"{STOP_TIMEOUT:g} s of being told to stop")


def _spot(i: int, per_row: int = 4, spacing: float = 1.5) -> tuple[float, float]:
    """Where player i stands (x, z metres): a grid, so that avatars do not overlap."""
    return ((i % per_row - (per_row - 1) / 2) * spacing, (i // per_row) * spacing)


async def run_players(url: str, players: int, seconds: float, motion: Path,
                      recorders: list[RecordingSource] | None = None,
                      devices: list[tuple[str, ...]] | None = None,
                      dropouts: DropoutSpec | None = None) -> list[PlayerStats]:
    """N players replaying the motion, all on one schedule (headsets tick together).
    ``recorders``: filled with the sources of the first MEASURED_PLAYERS, which keep
    what they captured. ``devices``: the players' tracker sets, in turn; ``dropouts``:
    each player loses devices at random (its own seed: seed + its number)."""
    sources: list[PoseSource] = []
    for i in range(players):  # the set simulated, not filtered frame by frame
        sources.append(BvhSource(motion, loop=True, rate_hz=HEADSET_HZ, offset=_spot(i),
                                 start_frame=37 * i, smooth=True,
                                 devices=devices[i % len(devices)] if devices else None))
    if recorders is not None:  # the true poses of the set, before any loss
        recording = [RecordingSource(s) for s in sources[:MEASURED_PLAYERS]]
        sources[:len(recording)] = recording
        recorders.extend(recording)
    if dropouts is not None:
        sources = [TrackerSetSource(s, dropouts=dataclasses.replace(
            dropouts, seed=dropouts.seed + i)) for i, s in enumerate(sources)]
    ticker = Ticker(sources[0].rate_hz) if sources else None
    try:
        return list(await asyncio.gather(*(
            run_player(url, ROOM, f"player {i + 1}", source, seconds=seconds, ticker=ticker)
            for i, source in enumerate(sources))))
    finally:
        for source in sources:
            source.close()


def _players_process(pipe: Connection, url: str, players: int, seconds: float,
                     motion: Path, cores: Cores, devices: list[tuple[str, ...]] | None,
                     dropouts: DropoutSpec | None) -> None:
    pin_to_cores("players", cores)
    pipe.recv()  # go: the spectators are in the room
    recorders: list[RecordingSource] = []
    try:
        stats = _run(run_players(url, players, seconds, motion, recorders, devices,
                                 dropouts))
    except SessionError as err:  # e.g. refused frames: a link's stall let too many pile up
        pipe.send(("error", str(err)))
        return
    logs = [r.log(p.avatar_id) for p, r in zip(stats, recorders, strict=False)]
    pipe.send([(p.frames_sent, dict(p.errors), log)
               for p, log in itertools.zip_longest(stats, logs)])


class _DemoSpectator(Spectator):
    """A headless spectator that tells when it is in the room and reads until the server
    closes the connection: it then has every frame the server handed to its socket."""

    def __init__(self, url: str, name: str, record: bool = False) -> None:
        super().__init__(url, ROOM, name)
        # set on the first roster: the server writes it and adds the spectator to the
        # room in one step, so every batch solved after that is offered to it
        self.in_room = asyncio.Event()
        # every batch as it came, for the display error (an append: nothing per frame)
        self.arrivals: list[Arrival] | None = [] if record else None

    def on_batch(self, batch: AvatarBatch, t_local: float, clock: ClockEstimator) -> None:
        super().on_batch(batch, t_local, clock)
        if self.arrivals is not None:
            self.arrivals.append(Arrival(t_local, clock.offset if clock.synced else None,
                                         batch))

    def on_roster(self, roster: AvatarRoster) -> None:
        super().on_roster(roster)
        self.in_room.set()

    async def run_until_closed(self) -> SpectatorStats:
        try:
            await self.run()
        except SessionError:  # the server closed the connection: the demo is over
            if self.session is None:  # it never joined
                raise
        finally:
            self.in_room.set()  # for whoever waits: it will not join any more
        return self.stats


async def run_clients(url: str, players: int, spectators: int, seconds: float,
                      motion: Path, render: Path | None = None,
                      render_mode: str = "interpolate", cores: Cores = (),
                      stop_server: Callable[[], None] = lambda: None,
                      spectator_urls: list[str] | None = None,
                      devices: list[tuple[str, ...]] | None = None,
                      dropouts: DropoutSpec | None = None,
                      browser: Mode | None = None) -> Clients:
    """Spectators here, players in a process of their own: a player's capture must not
    wait behind spectators decoding (on separate machines it would not). Once the players
    are done it calls ``stop_server``; the spectators end when the server closes their
    connections (``EmbeddedServer.stop``). ``spectator_urls``: the spectators spread
    over these servers in turn (the processes of one service); by default ``url``.
    ``browser``: the browser page too, in that playout mode (Chromium, its own process)."""
    far = spectator_urls or [url]
    watchers = [_DemoSpectator(far[i % len(far)], f"spectator {i + 1}", record=i == 0)
                for i in range(spectators)]
    spectator_tasks = [asyncio.create_task(w.run_until_closed()) for w in watchers]
    ctx = mp.get_context("spawn")
    pipe, child = ctx.Pipe()
    process = ctx.Process(target=_players_process, args=(child, url, players, seconds,
                                                         motion, cores, devices, dropouts),
                          daemon=True)
    process.start()
    child.close()  # the child's end is the child's: its exit is then our EOF
    viewer = (HeadlessViewerProcess(url, ROOM, render, mode=Mode(render_mode))
              if render is not None else None)
    if viewer is not None:  # a viewer of its own process: drawing holds the GIL
        await viewer.__aenter__()
    page = (BrowserSpectator(f"http{url.removeprefix('ws')}/?room={ROOM}&mode="
                             f"{browser.value}&record=1") if browser is not None else None)
    page_result: dict[str, Any] | None = None
    try:
        if page is not None:
            page.__enter__()
        # every spectator in the room before the first frame, so that each is offered
        # every batch (and the players' imports done meanwhile)
        await asyncio.wait_for(asyncio.gather(
            asyncio.sleep(1.0), *(w.in_room.wait() for w in watchers),
            *([asyncio.to_thread(page.wait_joined)] if page is not None else [])),
            JOIN_TIMEOUT)
        for task in spectator_tasks:
            if task.done():
                task.result()  # one that could not join: its SessionError
        pipe.send("go")
        loop = asyncio.get_running_loop()
        ready = asyncio.Event()
        loop.add_reader(pipe.fileno(), ready.set)
        try:
            await asyncio.wait_for(ready.wait(), seconds + 60)
        finally:
            loop.remove_reader(pipe.fileno())
        # the loop made the pipe non-blocking; the players' capture logs span many reads.
        # Read, and wait for the process to end, off the loop: the spectators are still
        # reading the last batches (a blocking join held them ~150 ms, the run's p99)
        os.set_blocking(pipe.fileno(), True)
        try:
            player_stats = await asyncio.to_thread(pipe.recv)
        except EOFError:
            raise DemoError("the players' process ended without a report") from None
        if isinstance(player_stats, tuple):  # ("error", why)
            raise DemoError(f"a player was disconnected: {player_stats[1]}")
        await asyncio.to_thread(process.join, 10)
        if page is not None:  # its recording, before the server closes its connection
            page_result = await asyncio.to_thread(page.finish)
    finally:
        if page is not None:
            await asyncio.to_thread(page.__exit__, None, None, None)
        if viewer is not None:
            await viewer.__aexit__(None, None, None)
        # the players have left; the server solves what is pending and empties the
        # outboxes before it closes: the spectators then read up to the close
        stop_server()
    spectator_stats = await asyncio.wait_for(asyncio.gather(*spectator_tasks),
                                             STOP_TIMEOUT)
    captures = [log for _, _, log in player_stats if log is not None]
    arrivals = (watchers[0].arrivals or []) if watchers else []
    return Clients(sum(sent for sent, _, _ in player_stats), list(spectator_stats),
                   viewer.result if viewer is not None else {}, captures, arrivals,
                   page_result)


@dataclass
class Clients:
    """What ``run_clients`` saw: the frames the players sent, the spectators' stats, the
    viewer's result, what the players captured, what spectator 1 received (for the
    display error) and the browser page's recording, stats and console errors."""

    frames_sent: int
    spectators: list[SpectatorStats]
    viewed: dict[str, Any]
    captures: list[CaptureLog]
    arrivals: list[Arrival]
    page: dict[str, Any] | None = None


def run_demo(players: int = 4, spectators: int = 2, seconds: float = 10.0,
             motion: Path | None = None, solver: str = "analytic",
             render: Path | None = None, render_mode: str = "interpolate",
             busy: bool | None = None, helper: bool | None = None,
             network: NetworkSpec | None = None,
             limits: ServerLimits | None = None, servers: int = 1,
             devices: list[str] | None = None,
             dropouts: DropoutSpec | None = None,
             browser: str | None = None) -> DemoResult:
    """The session; with ``render``, a headless viewer also draws the room to PNG files
    there and its ``capture_to_render`` joins the latency stages. ``busy``: the server
    busy-polls (``server.busy``); by default when it has a core of its own. ``helper``:
    a solver helper thread on the clients' core (``server.helper``); by default with
    busy polling. ``network``: every client connects through the emulator (its own
    process, on the clients' cores), delayed both ways. ``servers`` > 1: that many
    server processes sharing the room through a Redis started here (``serve --redis``):
    the players on the first, which owns the room; the spectators spread over all, and
    the others' ``relay`` hop (published to received) joins the latency stages.
    ``devices``: the players' tracker sets (``--devices`` specs), taken in turn;
    ``dropouts``: every player loses devices at random. ``browser``: the browser page
    joins too, in this playout mode (headless Chromium; BrowserMissingError without it), and
    its display error is measured beside the desktop modes'."""
    browser_mode = Mode(browser) if browser is not None else None
    if browser_mode is not None:
        find_chromium()  # before any process starts: one line that says how to get it
    motion = motion or builtin_motion_path()
    devices = devices or [DEFAULT_SET]
    sets = [parse_devices(d) for d in devices]
    cores = demo_cores()
    if busy is None:  # pin_to_cores gives the server the first core alone; with
        # --servers they share it (and Redis), where polling would starve the others
        busy = len(cores) >= 2 and servers == 1
    if servers > 1 and helper is None:
        helper = False  # its thread would spin on the clients' core
    with contextlib.ExitStack() as stack:
        redis_url = None
        if servers > 1:
            from posecast.client.bench.redis_process import RedisProcess
            redis_url = stack.enter_context(RedisProcess(
                setup=partial(pin_to_cores, "server", cores))).url
        try:
            server = stack.enter_context(EmbeddedServer(solver, cores, busy, helper, limits,
                                                        redis_url))
            # the others (and Redis) on the servers' core too, apart from the clients,
            # as on machines of their own (docs/performance.md, "Many processes")
            others = [stack.enter_context(EmbeddedServer(solver, cores, False, False,
                                                         limits, redis_url))
                      for _ in range(servers - 1)]
            proxy = stack.enter_context(_network(server.port, network, cores))
            pin_to_cores("spectators", cores)  # they run here (see run_clients)
            url = proxy.url if proxy is not None else server.url

            def stop_others() -> None:
                for other in others:
                    other.stop()

            def stop_servers() -> None:
                server.stop()
                if others:  # once the owner's last batches have crossed Redis
                    threading.Timer(RELAY_SETTLE_S, stop_others).start()
            clients = _run(run_clients(
                url, players, spectators, seconds, motion, render, render_mode,
                cores, stop_servers, [url, *(o.url for o in others)], sets, dropouts,
                browser_mode))
        finally:
            if cores:
                os.sched_setaffinity(0, cores)
    spectator_stats, viewed = clients.spectators, clients.viewed
    latency = LatencyRecorder.merged(s.latency for s in spectator_stats)
    for stage, samples in viewed.get("samples", {}).items():
        latency.add_values(stage, samples)
    every = [server.metrics, *(o.metrics for o in others)]
    relay = [v for m in every[1:] for v in m.get("relay_samples", [])]  # type: ignore[attr-defined]
    if relay:
        latency.add_values("relay", relay)
    metrics = server.metrics

    def total(name: str) -> int:
        return sum(int(m.get(name, 0)) for m in every)  # type: ignore[call-overload]
    rejected = metrics.get("rejected", {})
    # after the session, from what was recorded: it cost the session nothing
    rig = _server_rig()
    display_error = measure_display_error(clients.captures, clients.arrivals, rig, solver)
    page = None
    if browser_mode is not None and clients.page is not None:
        page = measure_page(clients.page, browser_mode, clients.captures, rig, solver)
        display_error.errors_mm["browser"] = page.errors_mm
    return DemoResult(
        players=players, spectators=spectators, seconds=seconds,
        frames_sent=clients.frames_sent,
        frames_solved=total("frames_solved"),
        frames_delivered=sum(s.frames_received for s in spectator_stats),
        frames_dropped=total("frames_dropped"),
        batches=total("batches"),
        rejected=dict(rejected) if isinstance(rejected, dict) else {},
        latency=latency, rendered=len(viewed.get("files", [])),
        frames_superseded=total("frames_superseded"),
        frames_discarded=total("frames_discarded"),
        frames_rejected=total("frames_rejected"),
        frames_unsendable=total("frames_unsendable"),
        viewer=render is not None, network=str(network) if network else "loopback",
        display_error=display_error, browser=page,
        clock_error_ms=clock_error_ms(clients.arrivals),
        metrics_display_error=metrics.get("display_error_mm", {}),  # type: ignore[arg-type]
        proxy=proxy.stats if proxy is not None else {}, servers=servers,
        frames_relayed=total("frames_relayed"),
        devices=[devices[i % len(devices)] for i in range(players)],
        dropouts=str(dropouts) if dropouts is not None else None,
        device_lost_frames=_per_role(every, "device_lost_frames"),
        device_losses=_per_role(every, "device_losses"))


def _per_role(metrics: list[dict[str, object]], name: str) -> dict[str, int]:
    """A per-role counter of the servers' metrics, summed."""
    out: dict[str, int] = {}
    for m in metrics:
        counts = m.get(name, {})
        if isinstance(counts, dict):
            for role, n in counts.items():
                out[role] = out.get(role, 0) + int(n)
    return out


def _server_rig() -> Rig:
    """The rig the embedded server solves with (``server.app.Session``'s default)."""
    return build_rig(load_makehuman().skeleton)


@contextmanager
def _network(port: int, spec: NetworkSpec | None, cores: Cores
             ) -> Iterator[ProxyProcess | None]:
    """The emulator in front of the server on ``port`` (nothing without a spec)."""
    if spec is None:
        yield None
        return
    with ProxyProcess(port, spec, setup=partial(pin_to_cores, "network", cores)) as proxy:
        yield proxy


def _run(coro: Coroutine[Any, Any, T]) -> T:
    """The clients' event loop: uvloop when installed."""
    from posecast.server.serving import install_fast_loop

    install_fast_loop()
    return asyncio.run(coro)
