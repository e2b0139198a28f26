"""The connections that do not play: spectators, who receive a room through their own
latest-wins outbox and may report what they presented, and replays, which publish a
recording's avatars into a room. ``Session`` inherits these handlers."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator

import numpy as np
from websockets.asyncio.server import ServerConnection, broadcast
from websockets.exceptions import ConnectionClosed

from posecast.protocol import (
    MAX_CLIENT_MESSAGE_BYTES,
    PROTOCOL_VERSION,
    AvatarBatch,
    AvatarRoster,
    Calibrate,
    ErrorCode,
    Hello,
    Leave,
    Ping,
    ProtocolError,
    TrackerFrame,
    ViewerReport,
    Welcome,
    decode,
    decode_client,
    encode,
)
from posecast.protocol.arrivals import arrival_time
from posecast.server.clock import now
from posecast.server.display_error import DisplayErrorMeter
from posecast.server.limits import (
    Budget,
    ServerLimits,
    frame_budget,
)
from posecast.server.metrics import Metrics
from posecast.server.outbox import Outbox
from posecast.server.replay import ReplayedAvatars
from posecast.server.room import (
    Delivery,
    Room,
    Spectator,
    send_deliveries,
)


class SpectatingConnections:
    """Session's handlers of spectators and replays (they read the session's state)."""

    limits: ServerLimits
    metrics: Metrics
    display: DisplayErrorMeter
    _ids: Iterator[int]

    async def _reject(self, ws: ServerConnection, err: ProtocolError) -> None:
        raise NotImplementedError

    async def _common(self, ws: ServerConnection, msg: object, t_received: float,
                      role: str) -> None:
        raise NotImplementedError

    async def _internal_error(self, ws: ServerConnection) -> None:
        raise NotImplementedError

    def _limited(self, limit: str, per_s: float, detail: str = "") -> ProtocolError:
        raise NotImplementedError

    # ------------------------------------------------------------------ replays
    async def _replay(self, ws: ServerConnection, conn_id: int, room: Room) -> None:
        """A recording's rosters and avatar batches published into the room
        (``server.replay``); its avatars leave with it. Each of its avatars has a player's
        frame budget (a recorded room's players were out of step: a batch each), rosters
        a player's calibration budget with a room's worth of burst."""
        limits = self.limits
        avatars = ReplayedAvatars(room, lambda: next(self._ids), limits, self.metrics)
        frames_per_s = limits.frames_per_s
        frames = frame_budget(limits, frames_per_s)
        rosters = Budget(limits.calibrations_per_s, limits.players_per_room)
        try:
            await ws.send(encode(Welcome(protocol_version=PROTOCOL_VERSION,
                                         connection_id=conn_id, avatar_id=None,
                                         server_time=now())))
            async for data in ws:
                t_received = arrival_time(ws, now)
                try:
                    msg = decode(data, max_bytes=MAX_CLIENT_MESSAGE_BYTES,
                                 codings=avatars.codings)
                    if isinstance(msg, AvatarBatch):
                        if not frames.take(t_received, msg.size):
                            raise self._limited("frames", frames_per_s)
                        avatars.batch(msg, t_received)
                    elif isinstance(msg, AvatarRoster):
                        if not rosters.take(t_received):
                            raise self._limited("calibrations", limits.calibrations_per_s)
                        avatars.roster(msg)
                        if frames_per_s != limits.frames_per_s * max(1, len(avatars.ids)):
                            frames_per_s = limits.frames_per_s * max(1, len(avatars.ids))
                            frames = frame_budget(limits, frames_per_s)
                    elif isinstance(msg, Ping | Leave):
                        await self._common(ws, msg, t_received, "replay")
                    else:
                        raise ProtocolError(ErrorCode.NOT_ALLOWED, f"a replay sends rosters "
                                            f"and avatar batches, not {msg.type}")
                except ProtocolError as err:
                    await self._reject(ws, err)
                except ConnectionClosed:
                    raise
                except Exception:  # a bug met by one message: it is answered, the rest goes on
                    await self._internal_error(ws)
        except ConnectionClosed:
            pass
        finally:
            avatars.close()

    # ------------------------------------------------------------------ spectators
    async def _spectator(self, ws: ServerConnection, conn_id: int, room: Room,
                         hello: Hello) -> None:
        async def send_bytes(data: bytes) -> None:
            await ws.send(data)

        async def send(deliveries: list[Delivery]) -> None:
            await send_deliveries(send_bytes, deliveries)
            self.metrics.frames_delivered += len(deliveries)

        outbox: Outbox[Delivery] = Outbox(send, hello.max_rate_hz)
        spectator = Spectator(outbox, send_bytes, connection=ws)
        try:
            await ws.send(encode(Welcome(protocol_version=PROTOCOL_VERSION,
                                         connection_id=conn_id, avatar_id=None,
                                         server_time=now())))
        except ConnectionClosed:  # gone right after its hello: nothing to undo yet
            return
        # the room's roster as it is now, written and the spectator joined in one step:
        # no roster change can fall between them, and no batch can come before the
        # roster its rotations unpack by
        parts = room.roster_messages(self.limits.roster_avatars_per_message,
                                     self.limits.roster_message_bytes)
        for part in parts:
            broadcast([ws], part)
        room.fanout.add(conn_id, spectator)
        spectator.task = asyncio.get_running_loop().create_task(outbox.run())
        reports = Budget(self.limits.reports_per_s, self.limits.report_burst)
        try:
            async for data in ws:
                t_received = arrival_time(ws, now)
                try:
                    msg = decode_client(data)
                    if isinstance(msg, TrackerFrame | Calibrate):
                        raise ProtocolError(ErrorCode.NOT_ALLOWED,
                                            f"a spectator only receives; {msg.type} is for "
                                            "players")
                    if isinstance(msg, ViewerReport):
                        if not reports.take(t_received):
                            raise self._limited("reports", self.limits.reports_per_s)
                        self._viewer_report(msg, t_received, room)
                        continue
                    await self._common(ws, msg, t_received, "spectator")
                except ProtocolError as err:
                    await self._reject(ws, err)
                except ConnectionClosed:
                    raise
                except Exception:  # a bug met by one message: it is answered, the rest goes on
                    await self._internal_error(ws)
        except ConnectionClosed:
            pass
        finally:
            room.spectators.pop(conn_id, None)
            # the batches it waited for, and what its outbox still holds: dropped
            self.metrics.frames_dropped += room.fanout.forget(spectator)
            outbox.close()
            task = spectator.task
            task.cancel()
            await asyncio.wait([task])  # and so does a send this cuts short
            if not task.cancelled():
                task.exception()  # retrieved: a send to a closed connection fails
            self.metrics.frames_dropped += outbox.dropped

    def _viewer_report(self, report: ViewerReport, t_received: float, room: Room) -> None:
        """A spectator's presentation times into the metrics, and its shown poses to
        the display error's samples, once every time is within ``capture_skew_s`` of
        the report's arrival: a viewer hours off, or one that reports the future, would
        spoil the histograms every scrape reads."""
        skew = self.limits.capture_skew_s
        shown = np.array([p.t_presented for p in report.shown])
        for name in ("t_capture", "t_received", "t_presented", "shown.t_presented"):
            times: np.ndarray = shown if name.startswith("shown") else getattr(report, name)
            if not times.size:
                continue
            off = np.flatnonzero(~(np.abs(times - t_received) <= skew))
            if off.size:
                row = int(off[0])
                raise ProtocolError(ErrorCode.INVALID, (
                    f"viewer_report.{name}[{row}]: {float(times[row])!r} is "
                    f"{float(times[row]) - t_received:+.3g} s off the server clock at its "
                    f"arrival; more than capture_skew_s ({skew:g} s): is the clock synced?"))
        self.metrics.viewer_reports += 1
        if report.shown:
            self.display.offer(room, report, t_received)
        if report.size:
            self.metrics.viewer_latency.report(report.t_capture, report.t_received,
                                               report.t_presented)
        if report.pose_to_submit is not None and report.pose_to_submit.size:
            self.metrics.headset_latency.observe(report.pose_to_submit[None, :])

