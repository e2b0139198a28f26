"""Where a demo server's time goes between a frame's arrival and its batch's send: loaded by
`scripts/ab_demo.py --parts` through PYTHONPATH, in every process of a demo of either
tree, so that neither tree's code changes for the measurement. Only with
POSECAST_AB_PARTS set (a file prefix); only in the process that imports the room module.

For each batch it appends one row per frame pending when the room began it, as float64:
the frame's arrival, when the room began the batch (its solve call), when the solve
started and ended, when the batch was first encoded (its t_sent) and the count of those
frames, to PREFIX.<pid>.f64. It wraps three
methods both trees have (Room._solve_and_deliver, AvatarSolver.solve_staged,
SharedBatch.encoded): each adds a few microseconds to a batch, on both sides alike.
"""

from __future__ import annotations

import importlib.abc
import importlib.util
import os
import sys
from collections.abc import Sequence
from importlib.machinery import ModuleSpec
from types import ModuleType
from typing import Any

ROOMS = ("posecast.server.room", "server.room")  # after the namespace move, and before
FLUSH_EVERY = 200  # batches: an embedded server ends with os._exit, buffers and all


def _instrument(room: ModuleType, prefix: str) -> None:
    import numpy as np  # loaded by the room module already; not at every start-up

    package = room.__name__.rsplit(".", 1)[0]
    now = sys.modules[f"{package}.clock"].now
    solver_class = sys.modules[f"{package}.avatars"].AvatarSolver
    out = open(f"{prefix}.{os.getpid()}.f64", "ab")  # noqa: SIM115 (open for the process)
    batch: dict[str, Any] = {}
    batches = 0

    solve_and_deliver = room.Room._solve_and_deliver
    solve_staged = solver_class.solve_staged
    encoded = room.SharedBatch.encoded

    def timed_solve_and_deliver(self: Any) -> None:
        nonlocal batches
        batch.clear()
        batch["began"] = now()
        arrivals = [t for _, t in self._pending.values()]
        solve_and_deliver(self)
        if "solve_start" in batch and "sent" in batch:
            n = len(arrivals)
            rows = np.empty((n, 6))
            rows[:, 0] = arrivals
            rows[:, 1:5] = (batch["began"], batch["solve_start"], batch["solve_end"],
                            batch["sent"])
            rows[:, 5] = n
            out.write(rows.tobytes())
            batches += 1
            if batches % FLUSH_EVERY == 0:
                out.flush()

    def timed_solve_staged(self: Any, avatar_ids: Sequence[int]) -> Any:
        batch["solve_start"] = now()
        solved = solve_staged(self, avatar_ids)
        batch["solve_end"] = now()
        return solved

    def timed_encoded(self: Any) -> bytes:
        if self._encoded is None and "sent" not in batch:
            batch["sent"] = now()  # the encoder stamps t_sent just after this
        return encoded(self)

    room.Room._solve_and_deliver = timed_solve_and_deliver
    solver_class.solve_staged = timed_solve_staged
    room.SharedBatch.encoded = timed_encoded


class _RoomFinder(importlib.abc.MetaPathFinder):
    """Instruments the room module as it is first imported."""

    def __init__(self, prefix: str) -> None:
        self.prefix = prefix

    def find_spec(self, name: str, path: Sequence[str] | None,
                  target: ModuleType | None = None) -> ModuleSpec | None:
        if name not in ROOMS:
            return None
        sys.meta_path.remove(self)  # the usual finders find it; then it is wrapped
        try:
            spec = importlib.util.find_spec(name)
        finally:
            sys.meta_path.insert(0, self)
        if spec is None or spec.loader is None:
            return spec
        loader, prefix = spec.loader, self.prefix
        execute = loader.exec_module

        def exec_module(module: ModuleType) -> None:
            execute(module)
            _instrument(module, prefix)

        loader.exec_module = exec_module  # type: ignore[method-assign]
        return spec


if os.environ.get("POSECAST_AB_PARTS"):
    sys.meta_path.insert(0, _RoomFinder(os.environ["POSECAST_AB_PARTS"]))
