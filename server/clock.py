"""The server clock: every timestamp of the chain is on it (clients convert with pings)."""

from __future__ import annotations

import time


def now() -> float:
    return time.perf_counter()
