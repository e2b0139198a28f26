"""The player: reads a pose source at its rate and streams tracker frames to the server.

``run_player`` connects, syncs its clock, sends a Calibrate (the source's T-pose), then one
TrackerFrame per slot of an absolute schedule (``Ticker``) until the source ends, the time
is up, ``stop`` is set or the task is cancelled; it then sends Leave. Error replies from
the server are logged and counted, not fatal: the next frame may well be fine.

The message builders (``calibrate_message``, ``tracker_frame``) are pure,
so tests check them without a server. Frames go out through ``encode_tracker_frame``, the
same bytes as ``encode(tracker_frame(...))`` without building the model, and are written
at once (``Session.send_now``): the capture's way to the socket stays short.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import cast

from posecast.client.session.connection import (
    Reconnect,
    Session,
    SessionError,
    make_hello,
    open_session,
    stop_task,
)
from posecast.client.sources.base import ROLES, DeviceSample, PoseSource, SourceError, now
from posecast.protocol import (
    Calibrate,
    DeviceRole,
    Error,
    ProtocolError,
    TrackerFrame,
    encode,
    encode_tracker_frame,
)

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- messages
def _roles(sample: DeviceSample) -> tuple[DeviceRole, ...]:
    # sources give plain strings; the message validates them against DeviceRole
    return cast(tuple[DeviceRole, ...], sample.roles)


def calibrate_message(sample: DeviceSample, clock_offset: float) -> Calibrate:
    """The Calibrate message of a T-pose sample (``clock_offset``: server - client, s)."""
    return Calibrate(roles=_roles(sample), poses=sample.poses,
                     t_capture=float(sample.t_capture), clock_offset=float(clock_offset))


def tracker_frame(seq: int, sample: DeviceSample, clock_offset: float) -> TrackerFrame:
    """The TrackerFrame of one sample; ``t_capture`` stays on the client clock."""
    return TrackerFrame(seq=seq, roles=_roles(sample), poses=sample.poses,
                        t_capture=float(sample.t_capture), clock_offset=float(clock_offset))


# --------------------------------------------------------------------------- pacing
# called at slot k: a player reads its source and writes its frame
SlotCallback = Callable[[int], None]


class Ticker:
    """An absolute schedule: slot k is due at ``start + k / rate_hz`` (``now()`` clock).

    Sleeping "one period" after each send would drift by every send's duration; firing
    at absolute slot times does not. Players subscribe a callback, called with the slot
    number at each slot. When the loop falls behind, the latest slot already due is
    served at once and the missed ones are skipped (never a burst of catch-up frames,
    which would only be stale poses).

    One Ticker may be shared by many players in one process (the demo's 16): one timer
    calls them one after the other, so their frames leave together, to be solved in one
    batch, with no task switch between one player's frame and the next (a task per
    player woken by a future spread 16 frames over ~0.7 ms, ~45 us each). Each player
    reads, encodes and writes in its turn, as on a machine of its own: reading every
    source first and then writing every frame kept the first frames waiting for the
    others' reads (the demo's capture_to_server p50 1.28 ms, against 0.22-0.36 in turn).
    A callback that raises is logged; the others keep their schedule.
    """

    def __init__(self, rate_hz: float, start: float | None = None,
                 clock: Callable[[], float] = now) -> None:
        if not (math.isfinite(rate_hz) and rate_hz > 0.0):
            raise ValueError(f"rate must be a positive number of Hz, got {rate_hz}")
        self.rate_hz = float(rate_hz)
        self.period = 1.0 / self.rate_hz
        self.start = start  # None: set by the first subscriber
        self.clock = clock
        self.last = -1  # the slot served last
        self._subscribers: list[SlotCallback] = []
        self._timer: asyncio.TimerHandle | None = None

    def slot_time(self, k: int) -> float:
        """When slot k is due; k * period, not a running sum, so no rounding drift."""
        assert self.start is not None
        return self.start + k * self.period

    def next_slot(self, last: int, t: float) -> int:
        """The slot to serve after ``last`` at time ``t``: ``last + 1``, or if that is
        already past, the latest slot due by ``t`` (the ones between are skipped)."""
        assert self.start is not None
        due = math.floor((t - self.start) * self.rate_hz)
        # rounding can put floor one off when t is (nearly) a slot time: trust slot_time
        if self.slot_time(due + 1) <= t:
            due += 1
        elif self.slot_time(due) > t:
            due -= 1
        return max(last + 1, due)

    def subscribe(self, callback: SlotCallback) -> None:
        """Call ``callback(k)`` at every slot k from the next one on (slot 0, at once,
        for the first subscriber of a new schedule)."""
        self._subscribers.append(callback)
        if self._timer is None:
            if self.start is None:
                self.start = self.clock()
            self._arm()

    def unsubscribe(self, callback: SlotCallback) -> None:
        if callback in self._subscribers:
            self._subscribers.remove(callback)
        if not self._subscribers and self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _arm(self) -> None:
        t = self.clock()
        k = self.next_slot(self.last, t)
        self._timer = asyncio.get_running_loop().call_later(
            max(self.slot_time(k) - t, 0.0), self._fire, k)

    def _fire(self, k: int) -> None:
        early = self.slot_time(k) - self.clock()
        if early > 0.0:  # uvloop rounds a timer to the nearest millisecond: not yet due
            self._timer = asyncio.get_running_loop().call_later(early, self._fire, k)
            return
        self.last = k
        for callback in list(self._subscribers):  # one may unsubscribe in its call
            try:
                callback(k)
            except Exception:  # a broken subscriber must not stop the others' schedule
                log.exception("ticker: a slot callback failed")
        self._timer = None
        if self._subscribers:
            self._arm()


# --------------------------------------------------------------------------- player
@dataclass
class PlayerStats:
    """What one player did; ``errors`` counts the server's Error replies by code."""

    frames_sent: int = 0
    calibrations_sent: int = 0
    slots_skipped: int = 0  # schedule slots missed because the loop ran late
    frames_dropped: int = 0  # frames not sent: the server had not read the ones before
    errors: Counter[str] = field(default_factory=Counter)
    last_error: str | None = None  # "code: message" of the latest Error
    connection_id: int | None = None
    avatar_id: int | None = None
    clock_offset: float = 0.0  # server - client, seconds, at the end
    clock_rtt: float = math.inf  # best round trip to the server, seconds
    seconds: float = 0.0  # from the first frame to the last
    ended_by: str = ""  # "source", "time", "stop", "cancel" or "server" (it went away)
    reconnects: int = 0  # sessions opened again after one was lost
    # the player's devices (those it calibrated with, or has sent since) missing from a
    # frame it sent, by role: frames without it, and times it was lost; and those
    # missing from the last frame
    lost_frames: Counter[str] = field(default_factory=Counter)
    losses: Counter[str] = field(default_factory=Counter)
    lost_now: tuple[str, ...] = ()
    devices: tuple[str, ...] = ()  # every device it has sent, in ROLES order

    def count_devices(self, roles: tuple[str, ...]) -> None:
        """A frame with these devices was sent."""
        if roles == self.devices:  # every frame of a player that lost nothing: done
            self.lost_now = ()
            return
        known = self.devices
        if any(r not in known for r in roles):
            known = self.devices = tuple(r for r in ROLES if r in known or r in roles)
        if len(roles) == len(known):
            self.lost_now = ()
            return
        lost = tuple(r for r in known if r not in roles)
        for role in lost:
            self.lost_frames[role] += 1
            if role not in self.lost_now:
                self.losses[role] += 1
        self.lost_now = lost


class Player:
    """One player connection streaming a pose source; see the module docstring.

    The caller owns ``source`` (opens and closes it). ``ticker``: a shared schedule (its
    rate should equal the source's); by default the player paces itself at
    ``source.rate_hz``.
    """

    def __init__(self, url: str, room: str, name: str, source: PoseSource,
                 token: str | None = None, ticker: Ticker | None = None,
                 cafile: Path | None = None, reconnect: Reconnect | None = None) -> None:
        self.url = url
        self.cafile = cafile  # a wss:// server's private CA (``open_session``)
        # its rate: the server allows that plus slack, not the rate of its fastest player
        self.hello = make_hello(url, "player", room, name, token, max_rate_hz=source.rate_hz)
        self.source = source
        self.ticker = ticker if ticker is not None else Ticker(source.rate_hz)
        if abs(self.ticker.rate_hz - source.rate_hz) > 1e-6 * source.rate_hz:
            log.warning("ticker at %g Hz but the source is %g Hz: playback speed changes",
                        self.ticker.rate_hz, source.rate_hz)
        self.stats = PlayerStats()
        self.session: Session | None = None
        # with a policy, a lost session is opened again and the avatar resumed
        self.reconnect = reconnect
        # a headset on this machine (client.headset) sees each sample read and each
        # T-pose sent, on this thread, as they go out
        self.on_sample: Callable[[DeviceSample], None] | None = None
        self.on_calibration: Callable[[DeviceSample], None] | None = None
        self._seq = 0
        self._recalibrate = False
        self._t_first: float | None = None  # the first frame's capture: ``seconds`` count

    def recalibrate(self) -> None:
        """Send a fresh Calibrate (the source's T-pose now) before the next frame."""
        self._recalibrate = True

    async def run(self, seconds: float | None = None,
                  stop: asyncio.Event | None = None) -> PlayerStats:
        """Stream until the source ends, ``seconds`` pass, ``stop`` is set or cancelled.

        A lost session raises SessionError, or with ``reconnect`` is opened again with
        the avatar's resume secret: the same avatar, calibrated, keeps streaming (a
        server that lost it gives a new one, which gets the T-pose again)."""
        session = await open_session(self.url, self.hello, cafile=self.cafile)
        while True:
            try:
                self.stats.ended_by = await self._run_session(session, seconds, stop)
                return self.stats
            except SessionError as lost:
                if self.reconnect is None or not lost.retry:
                    self.stats.ended_by = "server"
                    raise
                resume = self.hello.model_copy(update={"resume": session.welcome.resume})
                try:
                    again = await self.reconnect.again(lost, resume, cafile=self.cafile,
                                                       stop=stop, url=self.url)
                except SessionError:
                    self.stats.ended_by = "server"
                    raise
                if again is None:
                    self.stats.ended_by = "stop"
                    return self.stats
                session = again
                self.stats.reconnects += 1

    async def _run_session(self, session: Session, seconds: float | None,
                           stop: asyncio.Event | None) -> str:
        """Sync the clock, calibrate unless the avatar was resumed, stream; why it ended."""
        self.session = session
        self.stats.connection_id = session.connection_id
        self.stats.avatar_id = session.avatar_id
        reader = asyncio.create_task(self._read_loop(session), name="posecast-player-read")
        try:
            session.start_clock_sync()
            await session.wait_synced()
            if not session.welcome.resumed:
                await self._send_calibration(session)
            return await self._stream(session, reader, seconds, stop)
        except asyncio.CancelledError:
            self.stats.ended_by = "cancel"
            raise
        finally:
            await stop_task(reader)  # its SessionError, if any, was raised by _stream
            self.stats.clock_offset = session.clock.offset
            self.stats.clock_rtt = session.clock.rtt
            await session.close(self.stats.ended_by)

    async def _stream(self, session: Session, reader: asyncio.Task[None],
                      seconds: float | None, stop: asyncio.Event | None) -> str:
        """Send a frame at every slot of the ticker; returns why it ended (or raises the
        reader's SessionError when the server went away)."""
        ended: asyncio.Future[str] = asyncio.get_running_loop().create_future()
        slot = -1
        # counted from the first frame of the first session: a reconnect does not add time
        t_first = self._t_first
        deadline = t_first + seconds if t_first is not None and seconds is not None \
            else math.inf

        def on_slot(k: int) -> None:
            nonlocal slot, deadline, t_first
            if ended.done():
                return
            if slot >= 0:
                self.stats.slots_skipped += k - slot - 1
            slot = k
            try:
                if reader.done():  # the server went away: reader holds the SessionError
                    reader.result()
                    ended.set_result("server")
                elif stop is not None and stop.is_set():
                    ended.set_result("stop")
                elif now() >= deadline:
                    ended.set_result("time")
                else:
                    made = self._make_frame(session)
                    if made is None:
                        ended.set_result("source")
                        return
                    sample, frame = made
                    self._send_frame(session, frame, sample.roles)
                    if t_first is None:
                        t_first = self._t_first = sample.t_capture
                        deadline = t_first + seconds if seconds is not None else math.inf
                    self.stats.seconds = sample.t_capture - t_first
            except Exception as exc:  # the reader's SessionError, a source's error
                ended.set_exception(exc)

        self.ticker.subscribe(on_slot)
        try:
            return await ended
        finally:
            self.ticker.unsubscribe(on_slot)

    def _make_frame(self, session: Session) -> tuple[DeviceSample, bytes] | None:
        """A slot's frame: a fresh calibration sent first if one was asked for, then the
        source's pose read (its capture time) and encoded, for ``_send_frame``. None when
        the source has ended."""
        if self._recalibrate:
            try:
                message = calibrate_message(self.source.calibration(), session.clock.offset)
            except SourceError as err:  # a hand not tracked now: the session goes on
                self._recalibrate = False
                log.warning("not recalibrated: %s", err)
            else:
                if session.send_now(encode(message)):  # else: next slot
                    self._recalibrate = False
                    self.stats.calibrations_sent += 1
                    self._calibrated(message)
        sample = self.source.read()
        if sample is None:
            return None
        if self.on_sample is not None:
            self.on_sample(sample)
        return sample, encode_tracker_frame(self._seq, sample.roles, sample.poses,
                                            sample.t_capture, session.clock.offset)

    def _send_frame(self, session: Session, frame: bytes, roles: tuple[str, ...]) -> None:
        """A slot's frame written at once, right after its read (dropped if it cannot be:
        the server is not keeping up, or going, and this pose is stale next time)."""
        if session.send_now(frame):
            self._seq += 1
            self.stats.frames_sent += 1
            self.stats.count_devices(roles)
        else:
            self.stats.frames_dropped += 1

    async def _send_calibration(self, session: Session) -> None:
        self._recalibrate = False
        message = calibrate_message(self.source.calibration(), session.clock.offset)
        await session.send(message)
        self.stats.calibrations_sent += 1
        self.stats.count_devices(message.roles)
        self._calibrated(message)

    def _calibrated(self, message: Calibrate) -> None:
        if self.on_calibration is not None:
            self.on_calibration(DeviceSample(message.t_capture, message.roles, message.poses))

    async def _read_loop(self, session: Session) -> None:
        """Consume what the server sends a player: Pongs (in receive), Errors."""
        while True:
            try:
                msg, _ = await session.receive()
            except ProtocolError as err:  # a reply we cannot decode: count, carry on
                self._count_error(f"client:{err.code}", err.message)
                continue
            if isinstance(msg, Error):
                self._count_error(msg.code, msg.message)

    def _count_error(self, code: str, message: str) -> None:
        self.stats.errors[code] += 1
        self.stats.last_error = f"{code}: {message}"
        # the first of each code is news; at 90 Hz the repeats would flood the log
        level = logging.WARNING if self.stats.errors[code] == 1 else logging.DEBUG
        log.log(level, "%s: server error %s", self.url, self.stats.last_error)


async def run_player(url: str, room: str, name: str, source: PoseSource,
                     seconds: float | None = None, token: str | None = None,
                     ticker: Ticker | None = None,
                     stop: asyncio.Event | None = None) -> PlayerStats:
    """Join ``room`` at ``url`` as ``name`` and stream ``source``; see ``Player``.

    Raises SessionError (one line: URL and reason) if the server cannot be reached,
    refuses the hello, or goes away mid-stream. The caller closes ``source``.
    """
    return await Player(url, room, name, source, token=token, ticker=ticker).run(seconds,
                                                                                 stop)
