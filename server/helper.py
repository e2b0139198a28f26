"""A solver helper: a thread on a spare core that takes half of each batch.

The server solves on its event loop's thread, and waking a worker thread costs more in
this VM than the work it takes over (``server.app``). A helper that never sleeps has no
wake-up: it spins in compiled code without the GIL (``solver.ik.shared``) and claims
avatars of each batch the server posts. It runs at SCHED_IDLE on a core the server is
not pinned to, so it only gets that core when nothing else there wants it: in the demo,
the core of the players and spectators, idle while a burst is solved (the players have
sent, the spectators wait for the batch). Where the helper is not running, the server
claims the whole batch itself. It costs the spare core's idle time, all of it.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time

import numpy as np
from numpy.typing import NDArray

from posecast.solver.ik.shared import READY, STOP, analytic_helper, new_control
from posecast.solver.tracking.layout import ND, STATE_SIZE

log = logging.getLogger("posecast.server")


def spare_cores() -> tuple[int, ...]:
    """Cores this process is not pinned to: where a helper can run without taking the
    server's core. Empty when the process may run on every core (or cannot tell)."""
    if not hasattr(os, "sched_getaffinity"):
        return ()
    mine = os.sched_getaffinity(0)
    return tuple(c for c in range(os.cpu_count() or 1) if c not in mine)


class SolveHelper:
    """The helper thread over one set of avatar arrays (``AvatarSolver``'s): started
    with them, stopped before they are replaced. The server posts a batch through
    ``batch_args`` (``solver.ik.shared.solve_analytic_shared``)."""

    def __init__(self, cores: tuple[int, ...], args: tuple[object, ...], capacity: int,
                 joints: int) -> None:
        """``args``: the solver's arguments over the whole arrays (``Solver.analytic_args``),
        then the tracking's (``AvatarSolver``).
        No ``cores``: no thread, the caller solves every avatar, through the same
        compiled code (the server's warm path keeps that code in the caches)."""
        self.cores = cores
        self.control = new_control()
        self.rows: NDArray[np.int64] = np.zeros(capacity, dtype=np.int64)
        # who solved each avatar of a batch, and the helper's own results: the pose, and
        # the tracking state, targets and weights where it filled them
        self._own = (np.zeros(capacity, dtype=np.int64), np.empty((capacity, joints, 4)),
                     np.empty((capacity, 3)), np.zeros(capacity, dtype=np.int64),
                     np.empty((capacity, STATE_SIZE)), np.empty((capacity, ND, 7)),
                     np.empty((capacity, ND)), np.zeros(capacity, dtype=np.bool_))
        self._args = args
        self.handed = 0  # avatars the helper solved, once it has stopped
        self._thread: threading.Thread | None = None
        if not cores:
            return
        # compiled (or loaded) here, not in the thread: that holds the GIL for a while,
        # and the thread would hold it while the server runs
        stopped = new_control()
        stopped[STOP] = 1
        analytic_helper(stopped, self.rows, *self._own, *self._args)
        self._tid = 0
        self._thread = threading.Thread(target=self._run, name="posecast-solve-helper",
                                        daemon=True)
        self._thread.start()
        # only once it runs compiled code, without the GIL, may it lose its core: a
        # thread that loses its core holding the GIL stops the server's loop with it
        while not self.control[READY] and self._thread.is_alive():
            time.sleep(0.0001)
        with contextlib.suppress(OSError):
            os.sched_setaffinity(self._tid, cores)
        with contextlib.suppress(AttributeError, OSError):
            os.sched_setscheduler(self._tid, os.SCHED_IDLE, os.sched_param(0))

    def batch_args(self, n: int) -> tuple[object, ...]:
        """``solve_analytic_shared``'s arguments for rows[:n]."""
        return (self.control, self.rows, n, *self._own, *self._args)

    def _run(self) -> None:
        self._tid = threading.get_native_id()
        self.handed = analytic_helper(self.control, self.rows, *self._own, *self._args)

    def stop(self, wait: bool = True) -> None:
        """End the thread; ``wait=False`` does not wait for it to return (it needs the
        GIL and a turn of its core for that, ~10 ms with the clients busy there; it takes
        no batch meanwhile, having no more posted to it)."""
        if self._thread is None:
            return
        # back to a normal thread first: it needs the GIL, and a core, to return
        with contextlib.suppress(AttributeError, OSError):
            os.sched_setscheduler(self._tid, os.SCHED_OTHER, os.sched_param(0))
        self.control[STOP] = 1
        if not wait:
            return
        self._thread.join(5.0)
        if self._thread.is_alive():  # it cannot block; it would be a bug
            log.error("the solver helper did not stop")
