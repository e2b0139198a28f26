"""Counters of one server process: what came in, what was solved and sent, what was
rejected and why, what was dropped for slow receivers."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

from posecast.protocol.roles import roles_of_bits
from posecast.server.display_error import DisplayErrorHistograms
from posecast.server.latency import (
    HEADSET_STAGES,
    RelayLatency,
    ServerLatency,
    StageHistograms,
    ViewerLatency,
)


@dataclass
class Metrics:
    connections: int = 0
    # every tracker frame received ends as exactly one of the five below (while its
    # burst is open, none yet; a stopped server has none open)
    frames_received: int = 0
    frames_superseded: int = 0  # a player's newer frame replaced an unsolved one
    frames_discarded: int = 0  # unsolved: its avatar left or recalibrated, or shutdown
    frames_rejected: int = 0  # answered with an Error (not calibrated, solver refused)
    frames_solved: int = 0  # and sent: in a batch offered to the room's spectators
    # solved, but a spectator's checks would refuse its row (a root beyond the world's
    # bound): dropped alone, so that the rest of its batch goes out
    frames_unsendable: int = 0
    # avatar-frames a replay connection published (server.replay): not solved here, but
    # offered to the spectators like solved ones
    frames_replayed: int = 0
    # ``serve --redis``: avatar-frames another process solved, received through Redis
    # and offered to this process's spectators like solved ones
    frames_relayed: int = 0
    batches: int = 0
    calibrations: int = 0  # T-poses taken (a refused one counts in ``rejected``)
    rosters: int = 0  # roster messages sent to a room's spectators (merged changes)
    internal_errors: int = 0  # bugs met by a message or a connection (never expected)
    # every solved avatar-frame offered to a spectator is exactly one of these two:
    # handed to its socket, or never sent (a newer one of the avatar replaced it in the
    # outbox, the avatar left, or the connection closed first)
    frames_delivered: int = 0
    frames_dropped: int = 0
    # writes to a spectator's socket that carried more than one batch: it waited for a
    # later slice of the fan-out while the next batch came (server.fanout)
    writes_merged: int = 0
    rejected: Counter[str] = field(default_factory=Counter)  # by ErrorCode
    # refusals by the ServerLimits field that made them: a rate (frames, calibrations,
    # errors: the connection closed) or a cap (rooms, players_per_room, ...)
    limited: Counter[str] = field(default_factory=Counter)
    # per solved avatar-frame, filled a batch at a time (Room); read by /metrics
    latency: ServerLatency = field(default_factory=ServerLatency)
    # the spectators' own stages, from their reports (ViewerReport); read by /metrics
    viewer_reports: int = 0  # reports taken (a refused one counts in ``rejected``)
    viewer_latency: ViewerLatency = field(default_factory=ViewerLatency)
    headset_latency: StageHistograms = field(
        default_factory=lambda: StageHistograms(HEADSET_STAGES))
    relay_latency: RelayLatency = field(default_factory=RelayLatency)
    # the avatars viewers showed against the solved ones (ViewerReport.shown): metres,
    # per viewer kind and playout mode; and what became of the samples (measured; not
    # measurable: no history around their instant; skipped: over a tick's reservoir)
    display_error: DisplayErrorHistograms = field(default_factory=DisplayErrorHistograms)
    display_samples: Counter[str] = field(default_factory=Counter)
    # an avatar's devices missing from its player's frames (never an error: the body
    # carries on), by role: tracker frames that lacked it, and losses (tracked in the
    # avatar's frame before, not in this one); devices mounted after calibration
    device_lost_frames: Counter[str] = field(default_factory=Counter)
    device_losses: Counter[str] = field(default_factory=Counter)
    devices_mounted: Counter[str] = field(default_factory=Counter)

    def count_losses(self, before: int, now: int) -> None:
        """A frame's lost devices (``now``, protocol.roles bits) after the avatar's last
        frame's (``before``)."""
        for role in roles_of_bits(now):
            self.device_lost_frames[role] += 1
        for role in roles_of_bits(now & ~before):
            self.device_losses[role] += 1

    def as_json(self) -> dict[str, object]:
        return {"connections": self.connections, "frames_received": self.frames_received,
                "frames_superseded": self.frames_superseded,
                "frames_discarded": self.frames_discarded,
                "frames_rejected": self.frames_rejected,
                "frames_solved": self.frames_solved,
                "frames_unsendable": self.frames_unsendable,
                "frames_replayed": self.frames_replayed,
                "frames_relayed": self.frames_relayed, "batches": self.batches,
                "calibrations": self.calibrations, "rosters": self.rosters,
                "internal_errors": self.internal_errors,
                "frames_delivered": self.frames_delivered,
                "frames_dropped": self.frames_dropped,
                "writes_merged": self.writes_merged,
                "viewer_reports": self.viewer_reports, "rejected": dict(self.rejected),
                "limited": dict(self.limited),
                "device_lost_frames": dict(self.device_lost_frames),
                "device_losses": dict(self.device_losses),
                "devices_mounted": dict(self.devices_mounted),
                "display_error_mm": self.display_error.as_json(),
                "display_samples": dict(self.display_samples)}
