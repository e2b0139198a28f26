"""Every limit of one server process, in one place (``ServerLimits``), and the per-connection
message budgets that enforce the rates (``Budget``).

The defaults hold the figures of issue 14 (docs/architecture.md, "Limits"): a hostile
client spoils neither its room nor anyone else's. ``posecast serve --limit NAME=VALUE``
overrides any of them; ``Session(limits=...)`` takes them.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from posecast.protocol.sizes import MAX_CLIENT_MESSAGE_BYTES


@dataclass(frozen=True)
class ServerLimits:
    # websockets refuses a frame over this at its header (close 1009) instead of reading
    # it: the protocol's largest client message plus room for an explicit too_large Error
    max_message_bytes: int = MAX_CLIENT_MESSAGE_BYTES + 512
    # messages websockets buffers per connection before it stops reading the socket:
    # 16 x 4.5 KiB is all one connection can make the server hold
    max_queue: int = 16
    # tracker frames per second per player: a 144 Hz headset with slack for jitter
    frames_per_s: float = 240.0
    # the frame budget is counted per window this long (the bucket refills whole): a
    # network stall up to about this long delivers its frames in one clump, all taken
    frame_window_s: float = 1.0
    # frames over the budget in one window: the first gets an Error, the rest are dropped
    # and counted without a reply each, so a stall's clump does not end the connection;
    # over this many times the budget, more than any stall holds, it is closed (1008)
    frame_flood_factor: float = 4.0
    # a player that declares its rate (hello.max_rate_hz) gets this many times that
    # (capped by frames_per_s): a 90 Hz player cannot send a 240 Hz one's solves
    frame_rate_slack: float = 1.5
    # a calibration costs ~1 ms of solve and a roster broadcast to every spectator
    calibrations_per_s: float = 1.0
    calibration_burst: int = 3  # a player retrying a T-pose a few times
    # and per remote address, so that many connections cannot add up a flood: 32 at once
    # (~40 ms of solve, a venue's players all starting together), then 4/s (~5 ms/s)
    address_calibrations_per_s: float = 4.0
    address_calibration_burst: int = 32
    # new connections (websocket upgrades) per remote address: a venue's players and
    # viewers all joining at once behind one NAT (connections_per_address), then 8/s.
    # Over it, the upgrade is answered 429 before any websocket exists (the cheapest
    # refusal): a reconnect loop cannot make the server work at its connection rate
    address_joins_per_s: float = 8.0
    address_join_burst: int = 128
    # per-address budgets outlive their connections (server.address_budgets) in a
    # table of at most this many addresses (IPv6 counted by /64), least recent first out
    addresses_remembered: int = 65536
    # clock-sync pings: a client sends a burst of 5 at start, then 1/s
    pings_per_s: float = 10.0
    ping_burst: int = 20
    # viewer reports (presentation times for /metrics) per spectator: a browser sends
    # one every 0.5 s; each costs a few numpy calls
    reports_per_s: float = 4.0
    report_burst: int = 8
    # rejected messages per second; once the bucket is empty the connection is closed
    # (1008): a client that keeps erring is not worth answering
    errors_per_s: float = 10.0
    error_burst: int = 20
    # a room's solve and every roster grow with its players
    players_per_room: int = 64
    # connected plus lingering (a leaving player's avatar waits the reconnect grace);
    # at the cap, the oldest lingering avatar goes first
    avatars_per_room: int = 128
    rooms: int = 256  # each room costs a roster and solver state
    connections: int = 1024  # file descriptors and handler tasks
    # one venue behind one NAT fits a full room of players and viewers
    connections_per_address: int = 128
    # a roster is split into messages of at most this many avatars and bytes, far below
    # a viewer's 1 MiB limit (53 joints: ~2 KB per avatar)
    roster_avatars_per_message: int = 16
    roster_message_bytes: int = 64 * 1024
    # roster changes of a room go out at most once per this interval, merged (the first
    # after a quiet spell at once): no join/leave pattern makes a spectator's roster
    # traffic follow an attacker's connection rate
    roster_interval_s: float = 0.05
    # a spectator that takes no frame for this long while frames wait for it is closed
    # (1013): it stopped reading or its link is dead, and latest-wins can do no more
    backlog_evict_s: float = 5.0
    # a player with no tracker frame for this long (counted from its join or its last
    # calibration) is closed (1008); its avatar leaves after the reconnect grace
    idle_player_s: float = 60.0
    # the kernel's send buffer of each accepted socket: small, so that a slow viewer's
    # backlog builds in the event loop, where latest-wins replaces stale frames
    send_buffer_bytes: int = 64 * 1024
    # unsent bytes the kernel may hold (TCP_NOTSENT_LOWAT) before the socket counts as
    # full: bytes in flight to a far viewer are not limited, a backlog is (docs/performance.md).
    # About one batch of 16 players (protocol 4: ~1.9 KB)
    send_unsent_bytes: int = 2048
    # rejections logged one by one per connection; then one summary line per interval,
    # and at most log_lines_per_interval such lines for the whole server
    log_first_rejections: int = 3
    log_interval_s: float = 10.0
    log_lines_per_interval: int = 50
    # a tracker frame's t_capture + clock_offset (its capture on the server clock) must
    # be within this of its arrival: a synced player's is milliseconds off; one an hour
    # off, or infinite, is forged and would spoil every viewer's latency figures
    capture_skew_s: float = 60.0
    # every device of a T-pose within this of the head: a body, not a kilometre-wide
    # rig whose solved roots leave the protocol's world (MAX_POSITION_M)
    body_extent_m: float = 3.0

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            # every numeric limit is a positive count, size, rate or time
            if isinstance(value, int | float) and not value > 0:
                raise ValueError(f"limit {f.name} must be positive, got {value!r}")
        if self.avatars_per_room < self.players_per_room:  # else connected ones overflow it
            raise ValueError(f"limit avatars_per_room ({self.avatars_per_room}) must be at "
                             f"least players_per_room ({self.players_per_room})")

    def with_text(self, pairs: list[str]) -> ServerLimits:
        """These limits with NAME=VALUE overrides (the command line's ``--limit``); a
        ValueError names a bad name or value in one line."""
        types = {f.name: f.type for f in dataclasses.fields(self)}
        changes: dict[str, Any] = {}  # each converted to its field's type below
        for pair in pairs:
            name, sep, text = pair.partition("=")
            name = name.strip().replace("-", "_")
            if not sep:
                raise ValueError(f"a limit is NAME=VALUE, got {pair!r}")
            if name not in types:
                raise ValueError(f"unknown limit {name!r}: one of {', '.join(types)}")
            kind = int if types[name] in (int, "int") else float
            try:
                changes[name] = kind(text)
            except ValueError:
                raise ValueError(f"limit {name} takes {'an integer' if kind is int else 'a number'}"
                                 f", got {text!r}") from None
        return dataclasses.replace(self, **changes)


def frame_budget(limits: ServerLimits, per_s: float) -> Budget:
    """A player's frame budget: ``per_s`` over windows of ``frame_window_s``."""
    return Budget(per_s, max(1, math.ceil(per_s * limits.frame_window_s)))


def player_frames_per_s(limits: ServerLimits, declared_hz: float | None) -> float:
    """Tracker frames per second a player may send: its declared rate plus slack, never
    above the server's ``frames_per_s``."""
    if declared_hz is None:
        return limits.frames_per_s
    return min(limits.frames_per_s, declared_hz * limits.frame_rate_slack)


class Budget:
    """A bucket of ``burst`` messages refilled whole every ``burst / per_s`` seconds: a
    message costs one float compare and one int decrement (no allocation on the frame
    path); the bucket being empty is the rejection."""

    __slots__ = ("burst", "left", "refill_at", "refused", "window")

    def __init__(self, per_s: float, burst: int) -> None:
        self.burst = burst
        self.window = burst / per_s
        self.left = burst
        self.refill_at = 0.0
        self.refused = 0  # messages refused in the current window

    def would_take(self, t: float) -> bool:
        """Whether ``take(t)`` would succeed; spends nothing."""
        return t >= self.refill_at or self.left > 0

    def take(self, t: float, n: int = 1) -> bool:
        """Spend ``n`` messages at time ``t`` (seconds); False (nothing spent) when fewer
        are left."""
        if t >= self.refill_at:
            self.left = self.burst
            self.refill_at = t + self.window
            self.refused = 0
        if self.left < n:
            self.refused += 1
            return False
        self.left -= n
        return True
