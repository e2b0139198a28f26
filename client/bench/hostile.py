"""`posecast bench hostile --attack NAME`: what one hostile client does to everyone else
(issue 14's acceptance figures).

A real server process; a bystander player replaying the built-in walk at 90 Hz (in its
own process, as a headset would be) and a bystander spectator watching it (here); then
the attacker, in a process of its own, for S seconds. Attacks 1, 5 and 6 of the issue run
in ANOTHER room than the bystanders (they must not slow the server for everyone); the
poison attacks (item 2) run in the SAME room (a bad row must not cost the others theirs).
Reported: the bystander's receive rate and worst gap, the bystander player's frames lost
(seqs in the window the spectator never got), and the server's RSS growth.
"""

from __future__ import annotations

import asyncio
import itertools
import math
import multiprocessing as mp
from collections import Counter
from collections.abc import Awaitable, Callable
from multiprocessing.connection import Connection
from typing import Any

import msgpack
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus
from websockets.protocol import State

from posecast.client.bench.target import TargetServer
from posecast.client.builtin import builtin_motion_path
from posecast.client.session.connection import SessionError
from posecast.client.session.player import calibrate_message, run_player
from posecast.client.session.spectator import Spectator
from posecast.client.sources.base import now
from posecast.client.sources.bvh_source import BvhSource
from posecast.protocol import (
    PROTOCOL_VERSION,
    AvatarBatch,
    AvatarRoster,
    ClockEstimator,
    Hello,
    Ping,
    encode,
)
from posecast.protocol.codec import encode_tracker_frame
from posecast.server.limits import ServerLimits

ATTACKS = ("calibrate-flood", "bad-messages", "big-frames", "poison-time",
           "poison-calibration", "hello-strings", "reconnect-calibrate", "join-leave")
# issue 14's item 2, and issue 27's: what reaches the spectators of the attacker's room
SAME_ROOM = frozenset({"poison-time", "poison-calibration", "hello-strings",
                       "reconnect-calibrate", "join-leave"})
BYSTANDER_ROOM = "bystander"
HOSTILE_ROOM = "hostile"
BYSTANDER_NAME = "bystander"
HEADSET_HZ = 90.0
JOIN_TIMEOUT = 60.0
ATTACK_GRACE_S = 20.0  # an attacker's last close may wait for the server's backlog
RSS_SAMPLE_S = 0.1
SETTLE_S = 1.0  # after the attack: what RSS the server keeps once the attacker is gone
POISON_REACH_M = 950.0  # inside the protocol's 1000 m: each position valid alone
BIG_FRAME_BYTES = 1 << 20
BIG_FRAME_CONNECTIONS = 10
# the acceptance figures
TARGET_RATE_HZ = 80.0
TARGET_GAP_MS = 100.0
TARGET_RSS_MB = 30.0
TARGET_LOST_PCT = 1.0
# issue 27's: ten clients of 1 MiB frames, a reconnect loop, a join-and-leave loop
TARGET_BIG_FRAMES_RATE_HZ = 85.0
TARGET_CPU_PCT = 50.0  # of one core, the server process over the attack
TARGET_ROSTERS_PER_S = 5.0  # "a few a second" at the room's spectator


# --------------------------------------------------------------------------- attacker
class _Tally:
    """What an attacker did and what came back."""

    def __init__(self) -> None:
        self.sent = 0
        self.connections = 0
        self.refused = 0  # connections the server would not open
        self.errors: Counter[str] = Counter()  # Error replies by code
        self.closes: Counter[str] = Counter()  # close codes (and reasons) it got

    def closed(self, exc: ConnectionClosed) -> None:
        close = exc.rcvd
        self.closes[f"{close.code} {close.reason}".strip() if close is not None
                    else "1006"] += 1

    def as_json(self) -> dict[str, object]:
        return {"messages_sent": self.sent, "connections": self.connections,
                "connections_refused": self.refused, "errors": dict(self.errors),
                "closes": dict(self.closes)}


def _hello(role: str, room: str, name: str) -> bytes:
    return encode(Hello(protocol_version=PROTOCOL_VERSION, role=role,  # type: ignore[arg-type]
                        room=room, display_name=name))


async def _drain(ws: ClientConnection, tally: _Tally) -> None:
    """Read (and count) the replies: an attacker that never reads would only slow its
    own flood, behind its full receive buffer."""
    async for data in ws:
        if isinstance(data, bytes):
            try:
                msg = msgpack.unpackb(data)
            except Exception:
                continue
            if isinstance(msg, dict) and msg.get("type") == "error":
                tally.errors[str(msg.get("code"))] += 1


Attack = Callable[[ClientConnection, _Tally, Callable[[], bool]], Awaitable[None]]


async def _connected(url: str, room: str, name: str, tally: _Tally, until: float,
                     attack: Attack) -> None:
    """Join ``room`` as a player and run ``attack``; when the server closes the
    connection, join again, until the loop time ``until``."""
    loop = asyncio.get_running_loop()

    def running() -> bool:
        return loop.time() < until

    while running():
        try:
            async with connect(url, compression=None, max_size=None,
                               open_timeout=10) as ws:
                tally.connections += 1
                await ws.send(_hello("player", room, name))
                await ws.recv()  # the welcome (or an error before the close)
                reader = asyncio.create_task(_drain(ws, tally))
                try:
                    await attack(ws, tally, running)
                # AttributeError: websockets' send on a transport the server just closed
                except (ConnectionClosed, AttributeError):
                    pass
                finally:
                    reader.cancel()
                if ws.state is not State.OPEN:  # the server closed it: how
                    await asyncio.wait_for(ws.wait_closed(), 10)
                    tally.closes[f"{ws.close_code} {ws.close_reason or ''}".strip()] += 1
        except ConnectionClosed as exc:
            tally.closed(exc)
        except AttributeError:  # websockets closing a transport already lost: counted
            pass
        except (OSError, InvalidHandshake, TimeoutError):
            tally.refused += 1
            await asyncio.sleep(0.01)


async def _reconnecting(url: str, tally: _Tally, running: Callable[[], bool],
                        session: Callable[[ClientConnection], Awaitable[None]]) -> None:
    """Connect, ``session``, drop the socket; again at once, as fast as the server
    answers (a refused upgrade too: an attacker does not wait)."""
    while running():
        try:
            ws = await connect(url, compression=None, max_size=None, open_timeout=10,
                               close_timeout=1)
        except InvalidStatus as refused:  # the join budget's 429
            tally.refused += 1
            tally.closes[f"HTTP {refused.response.status_code}"] += 1
            continue
        except (OSError, InvalidHandshake, TimeoutError):  # dropped as it was accepted
            tally.refused += 1
            tally.closes["dropped"] += 1
            continue
        tally.connections += 1
        try:
            await session(ws)
        except ConnectionClosed as exc:
            tally.closed(exc)
        except AttributeError:  # websockets writing to a transport the server dropped
            pass
        finally:
            if ws.transport is not None:
                ws.transport.abort()


def _hostile_hellos() -> list[bytes]:
    """Player and spectator Hellos into the bystander's room (it holds an avatar, whose
    resume secret a player's is compared with) with each string field beyond ASCII,
    with control characters, forged log lines, long or empty (issue 27, item 1)."""
    values = ["é", "\U0001f600", "\x00\x1b[31m", "a\nINFO posecast.server: forged",
              "\u00e9" * 300, ""]
    hellos = []
    for role in ("player", "spectator"):
        for field in ("room", "display_name", "token", "resume"):
            for value in values:
                raw = {"type": "hello", "protocol_version": PROTOCOL_VERSION, "role": role,
                       "room": BYSTANDER_ROOM, "display_name": "hostile", field: value}
                hellos.append(msgpack.packb(raw))
    return hellos


def _source(offset: tuple[float, float]) -> BvhSource:
    return BvhSource(builtin_motion_path(), loop=True, rate_hz=HEADSET_HZ, offset=offset)


def _calibration_bytes(scale: float = 1.0) -> bytes:
    """The walk's T-pose; with ``scale``, stretched about the origin: each position still
    within the protocol's bound, the skeleton ~1 km across (issue 14, item 2)."""
    source = _source((0.0, 0.0) if scale != 1.0 else (3.0, 0.0))  # beside the bystander
    try:
        message = calibrate_message(source.calibration(), 0.0)
    finally:
        source.close()
    raw = msgpack.unpackb(encode(message))
    raw["poses"] = _scaled(raw["poses"], scale)
    return msgpack.packb(raw)


def _scaled(poses: bytes, scale: float) -> bytes:
    import numpy as np

    from posecast.protocol.validation import pose_wire, wire_pose_rows

    array = wire_pose_rows(poses)
    if scale != 1.0:  # centred over the origin, then as large as the bound allows
        array[:, [0, 2]] -= array[:, [0, 2]].mean(axis=0)
        reach = float(np.linalg.norm(array[:, :3], axis=1).max())
        array[:, :3] *= min(scale, POISON_REACH_M / reach)
    return pose_wire(array)


def _bad_messages() -> list[bytes]:
    """Malformed messages of every kind protocol/ rejects (item 5), two that crashed the
    Error reply on main (item 4), and one that tried to forge a log line."""
    ping = {"type": "ping", "t0": 1.0}
    return [b"\xc1 not msgpack", msgpack.packb([1, 2, 3]),
            msgpack.packb({"type": "nonsense"}), msgpack.packb({**ping, "t0": "x"}),
            msgpack.packb({**ping, "bad\nINFO posecast.server: forged": 1}),
            msgpack.packb({**ping, "k" * 1000: 1}),
            msgpack.packb({**ping, "t0": _nested(1000)}),
            msgpack.packb({"type": "tracker_frame", "seq": -1})]


def _nested(depth: int) -> object:
    value: object = 0
    for _ in range(depth):
        value = [value]
    return value


async def _flood(ws: ClientConnection, messages: list[bytes], tally: _Tally,
                 running: Callable[[], bool]) -> None:
    i = 0
    while running() and ws.state is State.OPEN:
        await ws.send(messages[i % len(messages)])  # waits only while the socket is full
        tally.sent += 1
        i += 1


async def _paced(ws: ClientConnection, tally: _Tally, running: Callable[[], bool],
                 first: bytes, frame: Callable[[int], bytes]) -> None:
    """``first`` (a calibration), then ``frame(seq)`` at a headset's rate."""
    await ws.send(first)
    tally.sent += 1
    loop = asyncio.get_running_loop()
    t0, seq = loop.time(), 0
    while running() and ws.state is State.OPEN:
        await ws.send(frame(seq))
        tally.sent += 1
        seq += 1
        await asyncio.sleep(max(0.0, t0 + seq / HEADSET_HZ - loop.time()))


def _poisoned_frames(scale: float, t_capture: float | None,
                     clock_offset: float | None) -> Callable[[int], bytes]:
    """Tracker frames, each valid field by field: with ``scale``, the stretched T-pose
    of the calibration held still; with times, the walk at times whose sum overflows."""
    if scale != 1.0:
        calibration = msgpack.unpackb(_calibration_bytes(scale))
        frames = [{**calibration, "type": "tracker_frame", "seq": 0}]
    else:
        source = _source((3.0, 0.0))
        samples = [source.read() for _ in range(int(HEADSET_HZ))]
        source.close()
        frames = [msgpack.unpackb(encode_tracker_frame(0, s.roles, s.poses, s.t_capture, 0.0))
                  for s in samples if s is not None]

    def frame(seq: int) -> bytes:
        raw = dict(frames[seq % len(frames)])
        raw["seq"] = seq
        if t_capture is not None:
            raw["t_capture"] = t_capture
        if clock_offset is not None:
            raw["clock_offset"] = clock_offset
        return msgpack.packb(raw)

    return frame


async def run_attack(url: str, attack: str, seconds: float) -> dict[str, object]:
    """One attack against ``url`` for ``seconds``; returns the attacker's tally. A
    server that stops answering does not hold the attacker: it gives up ATTACK_GRACE_S
    after its time, and says so (``timed_out``)."""
    tally = _Tally()
    try:
        await asyncio.wait_for(_attack(url, attack, seconds, tally), seconds + ATTACK_GRACE_S)
    except TimeoutError:
        return {**tally.as_json(), "timed_out": True}
    return {**tally.as_json(), "timed_out": False}


async def _attack(url: str, attack: str, seconds: float, tally: _Tally) -> None:
    loop = asyncio.get_running_loop()
    until = loop.time() + seconds

    def running() -> bool:
        return loop.time() < until

    if attack == "calibrate-flood":
        calibration = [_calibration_bytes()]

        async def flood_calibrations(ws: ClientConnection, t: _Tally,
                                     running: Callable[[], bool]) -> None:
            await _flood(ws, calibration, t, running)
        await _connected(url, HOSTILE_ROOM, "flooder", tally, until, flood_calibrations)
    elif attack == "bad-messages":
        bad = _bad_messages()

        async def flood_bad(ws: ClientConnection, t: _Tally,
                            running: Callable[[], bool]) -> None:
            await _flood(ws, bad, t, running)
        await _connected(url, HOSTILE_ROOM, "garbler", tally, until, flood_bad)
    elif attack == "big-frames":
        big = [bytes(BIG_FRAME_BYTES)]

        async def flood_big(ws: ClientConnection, t: _Tally,
                            running: Callable[[], bool]) -> None:
            await _flood(ws, big, t, running)
        await asyncio.gather(*(
            _connected(url, HOSTILE_ROOM, f"big {i}", tally, until, flood_big)
            for i in range(BIG_FRAME_CONNECTIONS)))
    elif attack == "hello-strings":
        hellos = itertools.cycle(_hostile_hellos())

        async def say_hello(ws: ClientConnection) -> None:
            await ws.send(next(hellos))
            tally.sent += 1
            reply = msgpack.unpackb(await ws.recv())
            if isinstance(reply, dict) and reply.get("type") == "error":
                tally.errors[str(reply.get("code"))] += 1
                await asyncio.wait_for(ws.wait_closed(), 10)
                tally.closes[f"{ws.close_code} {ws.close_reason or ''}".strip()] += 1
            else:
                await ws.close()
        await _reconnecting(url, tally, running, say_hello)
    elif attack == "reconnect-calibrate":
        join = _hello("player", BYSTANDER_ROOM, "recaller")
        tpose, ping = _calibration_bytes(), encode(Ping(t0=0.0))

        async def calibrate_and_drop(ws: ClientConnection) -> None:
            await ws.send(join)
            await ws.recv()  # the welcome
            for _ in range(3):
                await ws.send(tpose)
            await ws.send(ping)  # its pong: the three were handled
            tally.sent += 5
            while (reply := msgpack.unpackb(await ws.recv())).get("type") != "pong":
                tally.errors[str(reply.get("code"))] += 1
        await _reconnecting(url, tally, running, calibrate_and_drop)
    elif attack == "join-leave":
        lurk = _hello("player", BYSTANDER_ROOM, "lurker")

        async def join_and_leave(ws: ClientConnection) -> None:
            await ws.send(lurk)
            tally.sent += 1
            await ws.recv()  # the welcome
            await ws.close()
        await _reconnecting(url, tally, running, join_and_leave)
    elif attack in SAME_ROOM:
        scale = 500.0 if attack == "poison-calibration" else 1.0
        first = _calibration_bytes(scale)
        frame = (_poisoned_frames(scale, None, None) if attack == "poison-calibration"
                 else _poisoned_frames(1.0, 1e308, 1e308))

        async def poison(ws: ClientConnection, t: _Tally,
                         running: Callable[[], bool]) -> None:
            await _paced(ws, t, running, first, frame)
        await _connected(url, BYSTANDER_ROOM, "poisoner", tally, until, poison)
    else:
        raise ValueError(f"unknown attack {attack!r}; one of {', '.join(ATTACKS)}")


def _attack_process(pipe: Connection, url: str, attack: str, seconds: float) -> None:
    _source((0.0, 0.0)).close()  # imports and the motion file read before "go"
    pipe.send("ready")
    pipe.recv()  # go
    try:
        pipe.send(asyncio.run(run_attack(url, attack, seconds)))
    except Exception as exc:  # the bench says what went wrong instead of waiting
        pipe.send({"failed": repr(exc)})
        raise


def _player_process(pipe: Connection, url: str, seconds: float) -> None:
    source = _source((0.0, 0.0))
    try:
        stats = asyncio.run(run_player(url, BYSTANDER_ROOM, BYSTANDER_NAME, source,
                                       seconds=seconds))
        pipe.send({"frames_sent": stats.frames_sent, "errors": dict(stats.errors)})
    except SessionError as err:
        pipe.send({"error": str(err)})
    finally:
        source.close()


# --------------------------------------------------------------------------- bystander
class _Watcher(Spectator):
    """The bystander spectator: when each frame of the bystander player's avatar came,
    with its seq."""

    def __init__(self, url: str) -> None:
        super().__init__(url, BYSTANDER_ROOM, "bystander spectator")
        self.avatar_id: int | None = None
        self.arrivals: list[tuple[float, int]] = []  # (local time, seq)
        self.rosters: list[float] = []  # when each roster message came (local time)
        self.seen = asyncio.Event()

    def on_roster(self, roster: AvatarRoster) -> None:
        super().on_roster(roster)
        self.rosters.append(now())
        if self.avatar_id in roster.removed:  # a previous run's bystander
            self.avatar_id = None
        # the newest bystander: a previous run's (killed, so kept for the reconnect
        # grace) holds the name, and this one's is then "bystander 2" (unique names)
        for info in roster.avatars:
            name = info.display_name
            if (name == BYSTANDER_NAME or name.startswith(BYSTANDER_NAME + " ")) and (
                    self.avatar_id is None or info.avatar_id > self.avatar_id):
                self.avatar_id = info.avatar_id

    def on_batch(self, batch: AvatarBatch, t_local: float, clock: ClockEstimator) -> None:
        super().on_batch(batch, t_local, clock)
        ids = batch.avatar_ids.tolist()
        if self.avatar_id in ids:
            self.arrivals.append((t_local, int(batch.seqs[ids.index(self.avatar_id)])))
            if len(self.arrivals) >= HEADSET_HZ:
                self.seen.set()


def bystander_figures(arrivals: list[tuple[float, int]], t0: float,
                      t1: float) -> dict[str, float]:
    """Rate, worst gap and frames lost of one avatar's arrivals in the window [t0, t1]:
    lost = seqs between the first and last received there that never arrived."""
    inside = [(t, s) for t, s in arrivals if t0 <= t <= t1]
    times = [t0] + [t for t, _ in inside] + [t1]
    gap = max(b - a for a, b in itertools.pairwise(times))
    seqs = {s for _, s in inside}
    span = max(seqs) - min(seqs) + 1 if seqs else 0
    return {"rate_hz": round(len(inside) / (t1 - t0), 1),
            "worst_gap_ms": round(gap * 1000.0, 1),
            "frames_received": len(inside), "frames_expected": span,
            "frames_lost_pct": round(100.0 * (span - len(seqs)) / span, 2) if span
            else 100.0}


async def _reply(pipe: Connection, timeout: float) -> Any:
    """The next message of a child process, polled: a thread blocked in recv would hold
    the event loop's shutdown if the child never answered."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while not pipe.poll():
        if loop.time() > deadline:
            raise TimeoutError(f"no word from the attacker within {timeout:g} s")
        await asyncio.sleep(0.02)
    return pipe.recv()


async def _sample_rss(server: TargetServer, samples: list[tuple[float, float, int]],
                      stop: asyncio.Event) -> None:
    while not stop.is_set():
        samples.append((now(), server.rss_mb(), server.open_fds()))
        await asyncio.sleep(RSS_SAMPLE_S)


async def _measure(server: TargetServer, attack: str, seconds: float) -> dict[str, object]:
    ctx = mp.get_context("spawn")
    loop = asyncio.get_running_loop()
    watcher = _Watcher(server.url)
    watching = asyncio.create_task(watcher.run())
    _player_pipe, child = ctx.Pipe()  # held: the player is killed, not asked, at the end
    player = ctx.Process(target=_player_process,
                         args=(child, server.url, seconds + 2 * SETTLE_S + 30.0), daemon=True)
    attack_pipe, attack_child = ctx.Pipe()
    attacker = ctx.Process(target=_attack_process,
                           args=(attack_child, server.url, attack, seconds), daemon=True)
    player.start()
    attacker.start()
    samples: list[tuple[float, float, int]] = []
    stop_sampling = asyncio.Event()
    try:
        await asyncio.wait_for(watcher.seen.wait(), JOIN_TIMEOUT)
        await _reply(attack_pipe, JOIN_TIMEOUT)
        rss_before, fds_before = server.rss_mb(), server.open_fds()
        counts_before = await loop.run_in_executor(None, server.metrics)
        cpu_before = server.cpu_s()
        sampler = asyncio.create_task(_sample_rss(server, samples, stop_sampling))
        t0 = now()
        attack_pipe.send("go")
        tally = await _reply(attack_pipe, seconds + ATTACK_GRACE_S + JOIN_TIMEOUT)
        if "failed" in tally:
            raise RuntimeError(f"the attacker failed: {tally['failed']}")
        t1 = now()
        cpu = server.cpu_s() - cpu_before
        await asyncio.sleep(SETTLE_S)
        stop_sampling.set()
        await sampler
        rss_after = server.rss_mb()
        figures = bystander_figures(watcher.arrivals, t0, t1)
        metrics = await loop.run_in_executor(None, server.metrics)
    finally:
        watching.cancel()
        await asyncio.gather(watching, return_exceptions=True)
        for process in (attacker, player):
            process.join(0.1)
            if process.is_alive():
                process.kill()
                process.join(5)
    during = [rss for _, rss, _ in samples if not math.isnan(rss)] or [rss_before]
    growth = max(during) - rss_before
    figures["decode_errors"] = sum(watcher.stats.errors.values())
    figures["rosters_per_s"] = round(
        sum(t0 <= t <= t1 for t in watcher.rosters) / (t1 - t0), 2)
    server_figures = _server_figures(counts_before, metrics, cpu, t1 - t0)
    return {
        # the window ends when the attacker is done: its last close waits for the server
        # to get through what it queued, which bystanders feel too
        "attack": attack, "attack_seconds": seconds, "seconds": round(t1 - t0, 3),
        "bystander": {"room": BYSTANDER_ROOM, "same_room_as_attacker": attack in SAME_ROOM,
                      **figures},
        "server": {"alive": server.alive, "rss_before_mb": round(rss_before, 1),
                   "rss_max_mb": round(max(during), 1),
                   "rss_after_mb": round(rss_after, 1),
                   "rss_growth_mb": round(growth, 1), "fds_before": fds_before,
                   "fds_max": max((f for _, _, f in samples), default=fds_before),
                   "rejected": metrics.get("rejected", {}), **server_figures},
        "attacker": tally,
        "targets": _targets(attack, figures, growth, server_figures, tally),
    }


def _server_figures(before: dict[str, Any], after: dict[str, Any], cpu_s: float,
                    seconds: float) -> dict[str, float]:
    """What the server did over the window: its CPU (% of one core), calibrations
    taken (per second after the address's burst: ServerLimits), internal errors."""
    limits = ServerLimits()
    taken = int(after.get("calibrations", 0)) - int(before.get("calibrations", 0))
    beyond_burst = max(0, taken - limits.address_calibration_burst)
    return {"cpu_pct": round(100.0 * cpu_s / seconds, 1), "calibrations": taken,
            "calibrations_per_s_after_burst": round(beyond_burst / seconds, 2),
            "internal_errors": int(after.get("internal_errors", 0))
            - int(before.get("internal_errors", 0))}


def _targets(attack: str, figures: dict[str, float], growth: float,
             server: dict[str, float], tally: dict[str, Any]) -> list[dict[str, object]]:
    """The issues' acceptance figures that apply to this attack, each with its verdict."""
    def target(figure: str, value: float, words: str, met: bool) -> dict[str, object]:
        return {"figure": figure, "value": value, "target": words, "met": met}

    if attack in SAME_ROOM:
        lost = figures["frames_lost_pct"]
        # issue 14's for a poisoned row; issue 27's attacks have their own figures (an
        # attacker that spins a core of two clumps the bystander player's sends too)
        targets = [target("frames_lost_pct", lost, f"< {TARGET_LOST_PCT:g}",
                          lost < TARGET_LOST_PCT)] if attack.startswith("poison") else []
        if attack == "hello-strings":
            crashes = sum(n for close, n in tally["closes"].items()
                          if close.startswith("1011"))
            targets += [target("closes_1011", crashes, "0", crashes == 0),
                        target("internal_errors", server["internal_errors"], "0",
                               server["internal_errors"] == 0)]
        if attack in ("reconnect-calibrate", "join-leave"):
            targets.append(target("cpu_pct", server["cpu_pct"], f"< {TARGET_CPU_PCT:g}",
                                  server["cpu_pct"] < TARGET_CPU_PCT))
        if attack == "reconnect-calibrate":
            per_s = ServerLimits().address_calibrations_per_s
            value = server["calibrations_per_s_after_burst"]
            targets.append(target("calibrations_per_s_after_burst", value, f"<= {per_s:g}",
                                  value <= per_s))
        if attack == "join-leave":
            rosters = figures["rosters_per_s"]
            targets.append(target("rosters_per_s", rosters, f"<= {TARGET_ROSTERS_PER_S:g}",
                                  rosters <= TARGET_ROSTERS_PER_S))
        return targets
    rate = TARGET_BIG_FRAMES_RATE_HZ if attack == "big-frames" else TARGET_RATE_HZ
    return [{"figure": "rate_hz", "value": figures["rate_hz"],
             "target": f">= {rate:g}", "met": figures["rate_hz"] >= rate},
            {"figure": "worst_gap_ms", "value": figures["worst_gap_ms"],
             "target": f"<= {TARGET_GAP_MS:g}",
             "met": figures["worst_gap_ms"] <= TARGET_GAP_MS},
            {"figure": "rss_growth_mb", "value": round(growth, 1),
             "target": f"< {TARGET_RSS_MB:g}", "met": growth < TARGET_RSS_MB}]


def bench_hostile(attack: str, seconds: float = 10.0, solver: str = "analytic"
                  ) -> dict[str, object]:
    """Run ``attack`` for ``seconds`` against a fresh server process; the report."""
    if attack not in ATTACKS:
        raise ValueError(f"unknown attack {attack!r}; one of {', '.join(ATTACKS)}")
    with TargetServer(solver) as server:
        return measure_attack(server, attack, seconds)


def measure_attack(server: TargetServer, attack: str, seconds: float) -> dict[str, object]:
    """``attack`` against a running ``server`` (tests share one between attacks; the
    command starts a fresh one for each, so that RSS growth is the attack's alone)."""
    return asyncio.run(_measure(server, attack, seconds))


def format_hostile_table(doc: dict[str, Any]) -> str:
    by, sv, at = doc["bystander"], doc["server"], doc["attacker"]
    where = "same room as" if by["same_room_as_attacker"] else "another room than"
    lines = [f"attack {doc['attack']} for {doc['attack_seconds']:g} s (window until the "
             f"attacker was done: {doc['seconds']:g} s); bystander in {where} the attacker",
             f"  {'figure':<26} {'value':>10}  {'target':>8}  met"]
    target = {t["figure"]: t for t in doc["targets"]}
    rows = [("rate_hz", "bystander receive rate Hz", by["rate_hz"]),
            ("worst_gap_ms", "worst gap between frames ms", by["worst_gap_ms"]),
            ("frames_lost_pct", "bystander player lost %", by["frames_lost_pct"]),
            ("rosters_per_s", "rosters/s to the bystander", by["rosters_per_s"]),
            ("rss_growth_mb", "server RSS growth MB", sv["rss_growth_mb"]),
            ("cpu_pct", "server CPU % of a core", sv["cpu_pct"]),
            ("calibrations_per_s_after_burst", "calibrations/s after burst",
             sv["calibrations_per_s_after_burst"]),
            ("internal_errors", "server internal errors", sv["internal_errors"])]
    if "closes_1011" in target:
        rows.append(("closes_1011", "connections closed 1011", target["closes_1011"]["value"]))
    for key, words, value in rows:
        t = target.get(key)
        lines.append(f"  {words:<26} {value:>10g}  {t['target'] if t else '-':>8}  "
                     + (("yes" if t["met"] else "NO") if t else "-"))
    lines.append(f"  server RSS {sv['rss_before_mb']:g} -> max {sv['rss_max_mb']:g} -> "
                 f"{sv['rss_after_mb']:g} MB after; fds {sv['fds_before']} -> max "
                 f"{sv['fds_max']}; alive: {'yes' if sv['alive'] else 'NO'}")
    lines.append(f"  attacker: {at['messages_sent']} messages on {at['connections']} "
                 f"connections ({at['connections_refused']} refused); errors "
                 f"{at['errors'] or '{}'}; closes {at['closes'] or '{}'}")
    lines.append(f"  server rejected: {sv['rejected'] or '{}'}; bystander decode errors: "
                 f"{by['decode_errors']}")
    return "\n".join(lines)
