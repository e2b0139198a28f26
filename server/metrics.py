"""Counters of one server process: what came in, what was solved and sent, what was
rejected and why, what was dropped for slow receivers."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field


@dataclass
class Metrics:
    connections: int = 0
    frames_received: int = 0
    frames_superseded: int = 0  # a player's newer frame replaced an unsolved one
    frames_solved: int = 0
    batches: int = 0
    frames_delivered: int = 0  # avatar-frames handed to spectator sockets
    frames_dropped: int = 0  # avatar-frames a slow spectator never got (latest-wins)
    rejected: Counter[str] = field(default_factory=Counter)  # by ErrorCode

    def as_json(self) -> dict[str, object]:
        return {"connections": self.connections, "frames_received": self.frames_received,
                "frames_superseded": self.frames_superseded,
                "frames_solved": self.frames_solved, "batches": self.batches,
                "frames_delivered": self.frames_delivered,
                "frames_dropped": self.frames_dropped, "rejected": dict(self.rejected)}
