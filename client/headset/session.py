"""A headset beside a player: its frame loop's thread, its spectator connection, its
reports, and what its HUD says.

``Headset`` is entered around a player's streaming (``posecast play --hmd`` and
``--hmd-out``). It opens a second connection to the room as a spectator, the others'
frames going into the snapshot buffers of ``view --mode predict``; starts the frame loop
(``view.HeadsetView``) on its own thread; sends the server a ViewerReport twice a second
with the frames' poses-to-submit and the others' frames as presented (``/metrics``).
What the player streams is unchanged: the capture-time poses of its source.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from types import TracebackType

from posecast.client.headset.displays import Display, SampleFeed
from posecast.client.headset.local_body import LocalBody
from posecast.client.headset.view import HeadsetStats, HeadsetView
from posecast.client.measure.reports import REPORT_INTERVAL_S, Reports
from posecast.client.session.connection import Reconnect, SessionError, stop_task
from posecast.client.session.player import Player
from posecast.client.sources.base import DeviceSample, now
from posecast.client.viewer.interpolation import Interpolator, Mode
from posecast.client.viewer.scene import SpectatorScene, ViewerSpectator
from posecast.protocol import AvatarBatch, AvatarRoster, ClockEstimator

log = logging.getLogger(__name__)

NOTE_S = 3.0  # a message (countdown, reconnecting) stays on the HUD this long
JOIN_POLL_S = 0.02  # the spectator joins once the player has


class HeadsetSpectator(ViewerSpectator):
    """A ViewerSpectator whose room the frame loop's thread reads under ``lock``."""

    def __init__(self, *args: object, lock: threading.Lock, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.lock = lock

    def on_batch(self, batch: AvatarBatch, t_local: float, clock: ClockEstimator) -> None:
        with self.lock:
            super().on_batch(batch, t_local, clock)

    def on_roster(self, roster: AvatarRoster) -> None:
        with self.lock:
            super().on_roster(roster)

    def forget_room(self) -> None:
        with self.lock:
            super().forget_room()


class PlayerLink:
    """The player as the frame loop sees it (``view.PlayerLink``): fed by the player's
    hooks on the session's thread; plain attribute reads on the loop's."""

    def __init__(self, player: Player, feed: SampleFeed | None) -> None:
        self.player = player
        self.feed = feed
        self._tpose: tuple[int, DeviceSample] | None = None
        self._note: tuple[float, str] | None = None
        player.on_calibration = self._calibrated
        if feed is not None:
            player.on_sample = feed.put

    def _calibrated(self, sample: DeviceSample) -> None:
        if self.feed is not None:
            self.feed.put_tpose(sample)
        n = 0 if self._tpose is None else self._tpose[0] + 1
        self._tpose = (n, sample)

    def say(self, text: str) -> None:
        """Show ``text`` on the HUD for a few seconds (the terminal's lines)."""
        self._note = (now(), text)

    @property
    def tpose(self) -> tuple[int, DeviceSample] | None:
        return self._tpose

    @property
    def avatar_id(self) -> int | None:
        return self.player.stats.avatar_id

    @property
    def name(self) -> str:
        return self.player.hello.display_name

    @property
    def status(self) -> str:
        note = self._note
        if note is not None and now() - note[0] < NOTE_S:
            return note[1]
        p = self.player
        room = p.hello.room
        if p.session is None:
            return f"connecting to {p.url}"
        if self._tpose is None:
            return f"room {room}: stand in a T-pose"
        return f"room {room}: streaming" + (f", {p.stats.reconnects} reconnects"
                                            if p.stats.reconnects else "")


class Headset:
    """``async with Headset(player, display, stop=...)`` around the player's streaming;
    see the module docstring. ``stop`` is set when the loop ends by itself (``frames``
    drawn, the display ended, or it failed: ``__aexit__`` raises its error).
    ``spectate``: False draws the player alone (no second connection)."""

    def __init__(self, player: Player, display: Display, feed: SampleFeed | None, *,
                 stop: asyncio.Event, mirror_distance: float | None = 2.0,
                 frames: int | None = None, spectate: bool = True,
                 body: LocalBody | None = None) -> None:
        self.player = player
        self.display = display
        self.feed = feed
        self.stop = stop
        self.link = PlayerLink(player, feed)
        self.lock = threading.Lock()
        self.reports = Reports("headset")
        self.spectator: HeadsetSpectator | None = None
        if spectate:
            self.spectator = HeadsetSpectator(
                player.url, player.hello.room, player.hello.display_name,
                Interpolator(Mode.PREDICT), token=player.hello.token, cafile=player.cafile,
                lock=self.lock)
            if player.reconnect is not None:
                self.spectator.reconnect = Reconnect(say=log.info)
        scene = SpectatorScene(self.spectator) if self.spectator is not None else None
        self.view = HeadsetView(display, self.link, scene, self.lock, body,
                                mirror_distance, frames, on_frame=self.reports.headset_frame)
        self._thread_stop = threading.Event()
        self._thread = threading.Thread(target=self.view.run, name="posecast-headset",
                                        args=(self._thread_stop, self._ended), daemon=True)
        self._tasks: list[asyncio.Task[None]] = []
        self._loop: asyncio.AbstractEventLoop | None = None

    @property
    def stats(self) -> HeadsetStats:
        return self.view.stats

    def _ended(self) -> None:  # on the loop's thread, as it returns
        if self._loop is not None and not self._loop.is_closed():
            self._loop.call_soon_threadsafe(self.stop.set)

    async def __aenter__(self) -> Headset:
        self._loop = asyncio.get_running_loop()
        self._thread.start()
        if self.spectator is not None:
            self._tasks.append(asyncio.create_task(self._spectate(self.spectator),
                                                   name="posecast-headset-spectate"))
            self._tasks.append(asyncio.create_task(self._report(self.spectator),
                                                   name="posecast-headset-report"))
        return self

    async def __aexit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                        tb: TracebackType | None) -> None:
        self._thread_stop.set()
        if self.feed is not None:
            self.feed.close()
        await asyncio.to_thread(self._thread.join)
        for task in self._tasks:
            await stop_task(task)
        self.display.close()
        if self.view.error is not None and kind is None:
            raise self.view.error

    async def _spectate(self, spectator: HeadsetSpectator) -> None:
        """The others, for as long as the headset runs; a lost connection is the
        player's to report (it has the same server)."""
        while self.player.session is None:  # the player says why it cannot connect
            await asyncio.sleep(JOIN_POLL_S)
        try:
            await spectator.run()
        except SessionError as err:
            log.warning("headset: the room's view is lost: %s", err)

    async def _report(self, spectator: HeadsetSpectator) -> None:
        reports = self.reports
        while reports.enabled:
            await asyncio.sleep(REPORT_INTERVAL_S)
            session = spectator.session
            if session is None:
                continue
            report = reports.take(session.clock)
            if report is None:
                continue
            try:
                await session.send(report)
            except SessionError:
                continue  # the connection is being made again
            reports.sent += 1
            if reports.stop_if_refused(spectator.stats.last_error):
                log.info("headset: this server does not take headset reports")
