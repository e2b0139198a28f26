"""``posecast vmc``: one avatar of a room sent as VMC protocol messages over UDP.

The VMC protocol (protocol.vmc.info: OSC over UDP, receivers such as VSeeFace, VNyan,
Warudo and Unity with EVMC4U, port 39539 by default) drives a VRM avatar from another
program. A headless spectator (``client.spectator``) follows the room; each new frame of
the chosen avatar becomes one OSC bundle, as the spec's Performer sends them:

- ``/VMC/Ext/OK`` (int) loaded = 1, (int) calibration state = 3 (calibrated), (int)
  calibration mode = 0 (normal): the V2.5 form, which EVMC4U reads; V2.7's fourth
  argument (tracking status) is one the reference itself does not implement.
- ``/VMC/Ext/T`` (float) seconds since this sender started.
- ``/VMC/Ext/Root/Pos`` (string) "root", (float) p.x p.y p.z, (float) q.x q.y q.z q.w:
  the point on the floor under the hips, no rotation. Receivers that follow the root but
  not bone positions still carry the avatar around the room.
- ``/VMC/Ext/Bone/Pos`` (string) Unity HumanBodyBones name, (float) p.x p.y p.z, (float)
  q.x q.y q.z q.w for each humanoid bone the avatar's skeleton has
  (``solver.humanoid``): local rotations away from VRM's T-pose, Unity axes; positions
  are the bone's offset from its parent in this avatar's T-pose, and the Hips' its
  height over the root.

Bundles are rate-limited (60 Hz by default, at most 200 Hz, the cap SlimeVR keeps
because receivers choke above it): a frame that comes before its slot waits for it, and
frames that come meanwhile replace it, so the newest pose goes out every slot.

Transport: python-osc's ``UDPClient``, whose socket is non-blocking: a datagram is
handed to the kernel or refused at once (counted in ``send_errors``), never waited for,
so it cannot stall the event loop. Its one blocking step, resolving a host name (which
it would also repeat on every send), is done once here by the loop's ``getaddrinfo``.
"""

from __future__ import annotations

import asyncio
import logging
import math
import socket
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message import OscMessage
from pythonosc.osc_message_builder import OscMessageBuilder
from pythonosc.udp_client import UDPClient

from posecast.client.session.spectator import ReceivedFrame, Spectator
from posecast.client.skeletons import skeleton_of
from posecast.client.sources.base import now
from posecast.protocol import AvatarBatch, AvatarInfo, AvatarRoster, ClockEstimator
from posecast.solver.humanoid import HumanoidMap, humanoid_map, humanoid_pose
from posecast.solver.skeleton import SkeletonError

log = logging.getLogger(__name__)

DEFAULT_PORT = 39539  # the VMC protocol's default receiver port
DEFAULT_RATE_HZ = 60.0
MAX_RATE_HZ = 200.0  # SlimeVR's cap: receivers (VSeeFace) choke above it
FIND_TIMEOUT_S = 10.0  # how long a named avatar may take to appear in the room
RESOLVE_TIMEOUT_S = 10.0
SPECTATOR_NAME = "vmc"
# /VMC/Ext/OK: model loaded, calibration state Calibrated, calibration mode normal
OK_ARGS = (1, 3, 0)


class VmcError(Exception):
    """A problem the user can fix (a bad target, an absent avatar); ``str()`` is one line."""


@dataclass
class VmcStats:
    """What ``run_vmc`` sent: bundles, the avatar's frames not sent (the rate limit or a
    newer frame replaced them), sends the kernel refused, and how long it ran."""

    bundles_sent: int = 0
    frames_skipped: int = 0
    send_errors: int = 0
    seconds: float = 0.0
    avatar_id: int | None = None
    avatar_name: str | None = None


def parse_target(text: str, default_port: int = DEFAULT_PORT) -> tuple[str, int]:
    """``HOST:PORT``, ``HOST`` or ``[IPv6]:PORT`` as (host, port); VmcError if malformed."""
    text = text.strip()
    host, port_text = text, ""
    if text.startswith("["):
        end = text.find("]")
        if end < 0 or (text[end + 1:] and not text[end + 1:].startswith(":")):
            raise VmcError(f"bad VMC target {text!r}: expected [IPv6]:PORT")
        host, port_text = text[1:end], text[end + 2:]
    elif text.count(":") == 1:
        host, port_text = text.split(":")
    port: Any = default_port
    if port_text:
        try:
            port = int(port_text)
        except ValueError:
            raise VmcError(f"bad VMC target {text!r}: the port {port_text!r} is not a "
                           f"number") from None
    check_target(host, port)
    return host, port


def check_target(host: str, port: int) -> None:
    """VmcError unless ``host`` could name a host and ``port`` is a UDP port."""
    if not isinstance(host, str) or not host or len(host) > 253 or any(
            c.isspace() or not c.isprintable() for c in host):
        raise VmcError(f"bad VMC receiver host {host!r}: expected a host name or an IP "
                       f"address")
    if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
        raise VmcError(f"bad VMC receiver port {port!r}: expected a number from 1 to 65535")


def check_options(rate_hz: float, seconds: float | None, avatar: str | None) -> None:
    if not (isinstance(rate_hz, int | float) and math.isfinite(rate_hz)
            and 0.0 < rate_hz <= MAX_RATE_HZ):
        raise VmcError(f"bad VMC rate {rate_hz!r}: expected more than 0 and at most "
                       f"{MAX_RATE_HZ:g} Hz (receivers choke above)")
    if seconds is not None and not (math.isfinite(seconds) and seconds > 0.0):
        raise VmcError(f"bad duration {seconds!r}: expected a positive number of seconds")
    if avatar is not None and not avatar.strip():
        raise VmcError("the avatar name is empty: give a display name, or none for the "
                       "room's first avatar")


async def resolve(host: str, port: int) -> tuple[socket.AddressFamily, str]:
    """The receiver's address family and numeric address, resolved without blocking."""
    loop = asyncio.get_running_loop()
    try:
        found = await asyncio.wait_for(
            loop.getaddrinfo(host, port, type=socket.SOCK_DGRAM), RESOLVE_TIMEOUT_S)
    except (OSError, TimeoutError) as err:
        reason = getattr(err, "strerror", None) or str(err) or "timed out"
        raise VmcError(f"cannot resolve the VMC receiver host {host!r}: {reason}") from None
    family, _, _, _, address = found[0]
    return family, str(address[0])


def vmc_bundle(hmap: HumanoidMap, rotations: NDArray[np.float64], root: NDArray[np.float64],
               t: float) -> OscBundle:
    """One frame (local rotations (J, 4), root position (3,)) as a VMC bundle."""
    pose = humanoid_pose(hmap, rotations, root)
    hips = pose.hips.tolist()
    positions = hmap.rest_local_positions.copy()
    positions[0] = (0.0, hips[1], 0.0)  # the Hips over the root, which is under them
    rows = np.concatenate([positions, pose.rotations], axis=1).tolist()
    bundle = OscBundleBuilder(IMMEDIATELY)
    bundle.add_content(_message("/VMC/Ext/OK", [(v, "i") for v in OK_ARGS]))
    bundle.add_content(_message("/VMC/Ext/T", [(t, "f")]))
    bundle.add_content(_message("/VMC/Ext/Root/Pos", [
        ("root", "s"), *((v, "f") for v in (hips[0], 0.0, hips[2], 0.0, 0.0, 0.0, 1.0))]))
    for name, row in zip(hmap.bones, rows, strict=True):  # one message per bone: OSC's way
        bundle.add_content(_message("/VMC/Ext/Bone/Pos",
                                    [(name, "s"), *((v, "f") for v in row)]))
    return bundle.build()


def _message(address: str, args: list[tuple[Any, str]]) -> OscMessage:
    builder = OscMessageBuilder(address)
    for value, kind in args:
        builder.add_arg(value, kind)
    return builder.build()


def pick_avatar(roster: dict[int, AvatarInfo], name: str | None) -> AvatarInfo | None:
    """The avatar named ``name`` (exactly, else ignoring case; the earliest joined if
    several), or the earliest joined when ``name`` is None; None if there is none."""
    avatars = sorted(roster.values(), key=lambda a: a.avatar_id)
    if name is None:
        return avatars[0] if avatars else None
    for same in (lambda a: a.display_name == name,
                 lambda a: a.display_name.casefold() == name.casefold()):
        found = [a for a in avatars if same(a)]
        if found:
            return found[0]
    return None


def absent_message(name: str, room: str, roster: dict[int, AvatarInfo]) -> str:
    names = sorted({a.display_name for a in roster.values()})
    present = ", ".join(repr(n) for n in names) if names else "none (the room is empty)"
    return f"no avatar named {name!r} in room {room!r}; avatars present: {present}"


class _Sender:
    """The UDP socket, the chosen avatar's humanoid map and the rate limit's slots."""

    def __init__(self, family: socket.AddressFamily, address: str, port: int,
                 rate_hz: float) -> None:
        self.client = UDPClient(address, port, family=family)
        self.period = 1.0 / rate_hz
        self.next_slot = -math.inf
        self.info: AvatarInfo | None = None
        self.hmap: HumanoidMap | None = None
        self.last: ReceivedFrame | None = None
        self.t0 = now()

    def use(self, info: AvatarInfo) -> None:
        """Follow this avatar (or its new skeleton, after a recalibration)."""
        try:
            self.hmap = humanoid_map(skeleton_of(info))
        except SkeletonError as err:
            raise VmcError(f"avatar {info.display_name!r}: its skeleton has no Unity "
                           f"humanoid bones: {err}") from None
        self.info = info

    def send(self, received: ReceivedFrame, stats: VmcStats) -> None:
        assert self.hmap is not None
        batch, row, _ = received
        start = int(np.sum(batch.joint_counts[:row]))
        rotations = batch.rotations[start:start + int(batch.joint_counts[row])]
        t = now()
        bundle = vmc_bundle(self.hmap, rotations, batch.roots[row], t - self.t0)
        try:
            self.client.send(bundle)
            stats.bundles_sent += 1
        except OSError as err:  # a full buffer or an unreachable network: the frame goes
            stats.send_errors += 1
            level = logging.WARNING if stats.send_errors == 1 else logging.DEBUG
            log.log(level, "VMC send failed: %s", err)
        self.last = received
        # slots every period; a send more than one period late (the stream paused)
        # starts them again from now
        late = t - self.next_slot >= self.period
        self.next_slot = t + self.period if late else self.next_slot + self.period

    def close(self) -> None:
        self.client.close()


class _VmcSpectator(Spectator):
    """A spectator that wakes the sender whenever a batch or a roster arrives."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.changed = asyncio.Event()

    def on_batch(self, batch: AvatarBatch, t_local: float, clock: ClockEstimator) -> None:
        super().on_batch(batch, t_local, clock)
        self.changed.set()

    def on_roster(self, roster: AvatarRoster) -> None:
        super().on_roster(roster)
        self.changed.set()


async def run_vmc(url: str, room: str, avatar: str | None = None, host: str = "127.0.0.1",
                  port: int = DEFAULT_PORT, seconds: float | None = None,
                  rate_hz: float = DEFAULT_RATE_HZ, token: str | None = None,
                  cafile: Path | None = None, stop: asyncio.Event | None = None,
                  find_timeout: float = FIND_TIMEOUT_S,
                  stats: VmcStats | None = None) -> VmcStats:
    """Spectate ``room`` at ``url`` and send one avatar to the VMC receiver at
    ``host``:``port`` until ``seconds`` pass or ``stop`` is set.

    ``avatar``: a display name (waited for up to ``find_timeout`` seconds, then VmcError
    naming the avatars present), or None for the room's first avatar (waited for as long
    as it runs). Raises VmcError for bad options or an unresolvable host, SessionError
    when the server cannot be reached or goes away. ``stats``: filled as it goes.
    """
    check_target(host, port)
    check_options(rate_hz, seconds, avatar)
    family, address = await resolve(host, port)
    stats = stats if stats is not None else VmcStats()
    spectator = _VmcSpectator(url, room, SPECTATOR_NAME, token=token, cafile=cafile)
    halt = asyncio.Event()
    watching = asyncio.create_task(spectator.run(seconds, halt), name="posecast-vmc-watch")
    relay = asyncio.create_task(_relay(stop, halt)) if stop is not None else None
    sender = _Sender(family, address, port, rate_hz)
    t_start = now()
    chosen: set[int] = set()
    try:
        await _send_loop(spectator, watching, sender, stats, chosen, room, avatar,
                         t_start + find_timeout)
    finally:
        halt.set()
        if relay is not None:
            relay.cancel()
        sender.close()
        stats.seconds = now() - t_start
        received = sum(spectator.stats.frames_per_avatar[a] for a in chosen)
        stats.frames_skipped = max(received - stats.bundles_sent - stats.send_errors, 0)
        # wait for the spectator to leave; its error, if any, is taken (not left unread)
        await asyncio.gather(watching, return_exceptions=True)
    watching.result()  # the SessionError of a server that went away, if any
    return stats


async def _relay(stop: asyncio.Event, halt: asyncio.Event) -> None:
    await stop.wait()
    halt.set()


async def _send_loop(spectator: _VmcSpectator, watching: asyncio.Task[Any], sender: _Sender,
                     stats: VmcStats, chosen: set[int], room: str, name: str | None,
                     find_deadline: float) -> None:
    found = False
    while not watching.done():
        spectator.changed.clear()
        info = pick_avatar(spectator.roster, name)
        if info is None:
            if name is not None and not found and now() >= find_deadline:
                raise VmcError(absent_message(name, room, spectator.roster))
            wait = None if name is None or found else find_deadline - now()
            await _wait(spectator.changed, watching, wait)
            continue
        if not found or info is not sender.info:
            found = True
            sender.use(info)
            chosen.add(info.avatar_id)
            stats.avatar_id, stats.avatar_name = info.avatar_id, info.display_name
            log.info("sending avatar %r (id %d) as VMC", info.display_name, info.avatar_id)
        received = spectator.latest.get(info.avatar_id)
        if received is None or received is sender.last:
            await _wait(spectator.changed, watching, None)
            continue
        delay = sender.next_slot - now()
        if delay > 0.0:  # newer frames that come meanwhile replace this one
            await _wait(None, watching, delay)
            continue
        sender.send(received, stats)


async def _wait(event: asyncio.Event | None, watching: asyncio.Task[Any],
                timeout: float | None) -> None:
    """Until ``event`` is set, ``watching`` ends, or ``timeout`` seconds pass."""
    waits: set[asyncio.Future[Any]] = {watching}
    waiter = asyncio.ensure_future(event.wait()) if event is not None else None
    if waiter is not None:
        waits.add(waiter)
    try:
        await asyncio.wait(waits, timeout=timeout, return_when=asyncio.FIRST_COMPLETED)
    finally:
        if waiter is not None:
            waiter.cancel()
