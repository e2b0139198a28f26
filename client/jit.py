"""The compiled kernels: build them ahead of use, and say so whenever they must compile.

numba compiles the solver and protocol kernels on first use and keeps them in an on-disk
cache (next to the sources, or in ``NUMBA_CACHE_DIR``). Compiling them all takes ~30-60 s
on a small machine, so ``make setup`` runs ``posecast warm`` (``warm_kernels``): later
commands load them from the cache in well under a second. Any command that still has to
compile (a new install, an edited kernel, another CPU) says so in one line and counts
the kernels as they compile (``CompileNotice``), instead of freezing without a word.
"""

from __future__ import annotations

import multiprocessing as mp
import queue
import sys
import time
import traceback
from collections.abc import Callable
from multiprocessing.queues import Queue
from typing import TextIO

from numba.core import event

Step = tuple[str, Callable[[], None]]
NOTICE = "compiling solver kernels, first run only"


class CompileNotice(event.Listener):
    """Listens to numba's compile events (cache loads send none): the first compile
    prints one line, a terminal then sees a running count, and ``close`` says how long
    it took. Installed for the whole process by ``install``."""

    def __init__(self, stream: TextIO | None = None) -> None:
        self.stream = stream or sys.stderr
        self.live = self.stream.isatty()
        self.compiled = 0
        self._depth = 0
        self._started: float | None = None
        self._status = ""
        self.step = ""  # what runs now, when warm_kernels drives it

    def on_start(self, event: event.Event | None) -> None:
        self._depth += 1  # numba's own helpers and a kernel's callees compile inside it
        if self._started is None:
            self._started = time.monotonic()
            self.stream.write(f"posecast: {NOTICE} (about a minute; `posecast warm` "
                              "does it ahead) ...\n")
            self.stream.flush()

    def on_end(self, event: event.Event | None) -> None:
        self._depth -= 1
        if self._depth > 0:
            return
        self.compiled += 1
        if self._started is not None:
            self.show(f"  {self.step}{self.compiled} kernels compiled, "
                      f"{time.monotonic() - self._started:.0f} s")

    def one_compiled(self) -> None:
        """A kernel compiled elsewhere (``warm_kernels``' workers): told and counted."""
        self.on_start(None)
        self.on_end(None)

    def show(self, status: str) -> None:
        """A status line that the next one overwrites (terminals only)."""
        if self.live:
            pad = " " * max(0, len(self._status) - len(status))
            self.stream.write(f"\r{status}{pad}")
            self.stream.flush()
            self._status = status

    def close(self) -> None:
        """End the status line and say what compiling cost, if anything compiled."""
        if self._status:
            self.stream.write("\r" + " " * len(self._status) + "\r")
            self._status = ""
        if self._started is not None and self._depth == 0:
            self.stream.write(f"posecast: compiled {self.compiled} kernels in "
                              f"{time.monotonic() - self._started:.1f} s; cached for "
                              "next time\n")
            self._started = None
            self.compiled = 0
        self.stream.flush()

    def install(self) -> CompileNotice:
        event.register("numba:compile", self)
        return self

    def uninstall(self) -> None:
        event.unregister("numba:compile", self)


def kernel_steps() -> list[Step]:
    """Every path that runs compiled code, each run once on the smallest real input, with
    the argument types the commands use (a kernel compiles once per type signature)."""
    from posecast.solver.choices import SOLVERS  # names alone: the caller compiles nothing

    def protocol() -> None:
        # the wire codec's kernels (and a replayed clip's) have fixed signatures:
        # importing compiles or loads them
        import posecast.client.sources.bvh_source
        import posecast.protocol.quantize
        import posecast.protocol.validation  # noqa: F401

    def evaluate(solver: str) -> Callable[[], None]:
        def run() -> None:
            from dataclasses import replace

            from posecast.client.builtin import builtin_motion_path
            from posecast.solver.evaluation import EvalOptions, evaluate_bvh
            from posecast.solver.readers.bvh import read_bvh

            motion = read_bvh(builtin_motion_path())
            first = motion.first_frame
            short = replace(motion, rotations=motion.rotations[:first + 3],
                            translations=motion.translations[:first + 3])
            evaluate_bvh(short, EvalOptions(solver=solver))
        return run

    def server() -> None:
        # the server's own solve: staged arrays, bone targets and the helper thread's loop
        from posecast.server.avatars import AvatarSolver
        from posecast.solver.readers.gltf import load_makehuman
        from posecast.solver.rig import build_rig

        rig = build_rig(load_makehuman().skeleton)
        for name in SOLVERS:
            avatars = AvatarSolver(rig, name, capacity=1, helper_cores=(0,))
            avatars.warm_up()
            avatars.close()

    return ([("wire codec", protocol)]
            + [(f"{name} solver", evaluate(name)) for name in SOLVERS]
            + [("server solve", server)])


def warm_kernels(notice: CompileNotice | None = None, workers: int = 1) -> float:
    """Compile (or load) every kernel now; returns the seconds it took. With a notice,
    a terminal sees which step runs. ``workers`` > 1: the steps run in that many
    processes of their own, which only fill the on-disk cache (``posecast warm``): one
    step compiles for minutes (the analytic solver's), the others meanwhile on another
    core."""
    start = time.monotonic()
    if workers > 1:
        _warm_in_workers(notice, workers)
        return time.monotonic() - start
    steps = kernel_steps()
    for i, (label, run) in enumerate(steps, 1):
        if notice is not None:
            notice.step = f"[{i}/{len(steps)}] {label}: "
        run()
    if notice is not None:
        notice.close()
    return time.monotonic() - start


class _Relay(event.Listener):
    """A worker's compiles, told to the parent (a kernel's callees compile inside it:
    only the outermost counts)."""

    def __init__(self, events: Queue[tuple[str, str]]) -> None:
        self.events = events
        self._depth = 0

    def on_start(self, event: event.Event) -> None:
        self._depth += 1

    def on_end(self, event: event.Event) -> None:
        self._depth -= 1
        if self._depth == 0:
            self.events.put(("compiled", ""))


def _worker(labels: Queue[str | None], events: Queue[tuple[str, str]]) -> None:
    """Run the steps named in ``labels`` until a None, telling ``events`` each compile,
    each step done, and a step's failure (its traceback)."""
    event.register("numba:compile", _Relay(events))
    steps = dict(kernel_steps())
    while (label := labels.get()) is not None:
        try:
            steps[label]()
        except BaseException:
            events.put(("failed", f"{label}: {traceback.format_exc()}"))
            return
        events.put(("done", label))


def _warm_in_workers(notice: CompileNotice | None, workers: int) -> None:
    """``kernel_steps`` taken in turn by ``workers`` processes; the notice counts their
    compiles as they come. RuntimeError naming the step if one fails."""
    ctx = mp.get_context("spawn")  # a fresh interpreter: numba's state is per process
    labels: Queue[str | None] = ctx.Queue()
    events: Queue[tuple[str, str]] = ctx.Queue()
    names = [label for label, _ in kernel_steps()]
    for label in names:
        labels.put(label)
    processes = [ctx.Process(target=_worker, args=(labels, events), daemon=True)
                 for _ in range(min(workers, len(names)))]
    for _ in processes:
        labels.put(None)
    for process in processes:
        process.start()
    done = 0
    try:
        while done < len(names):
            try:
                kind, what = events.get(timeout=1.0)
            except queue.Empty:
                if not any(p.is_alive() for p in processes):
                    raise RuntimeError("a kernel worker ended without a word") from None
                continue
            if kind == "failed":
                raise RuntimeError(f"compiling kernels failed in {what}")
            if kind == "done":
                done += 1
                if notice is not None:
                    notice.step = f"[{done}/{len(names)} steps] "
            elif notice is not None:
                notice.one_compiled()
    finally:
        for process in processes:
            process.join(10)
            if process.is_alive():
                process.kill()
    if notice is not None:
        notice.close()
