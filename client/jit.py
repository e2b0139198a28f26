"""The compiled kernels: build them ahead of use, and say so whenever they must compile.

numba compiles the solver and protocol kernels on first use and keeps them in an on-disk
cache (next to the sources, or in ``NUMBA_CACHE_DIR``). Compiling them all takes ~30-60 s
on a small machine, so ``make setup`` runs ``posecast warm`` (``warm_kernels``): later
commands load them from the cache in well under a second. Any command that still has to
compile (a new install, an edited kernel, another CPU) says so in one line and counts
the kernels as they compile (``CompileNotice``), instead of freezing without a word.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
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

    def on_start(self, event: event.Event) -> None:
        self._depth += 1  # numba's own helpers and a kernel's callees compile inside it
        if self._started is None:
            self._started = time.monotonic()
            self.stream.write(f"posecast: {NOTICE} (about a minute; `posecast warm` "
                              "does it ahead) ...\n")
            self.stream.flush()

    def on_end(self, event: event.Event) -> None:
        self._depth -= 1
        if self._depth > 0:
            return
        self.compiled += 1
        if self._started is not None:
            self.show(f"  {self.step}{self.compiled} kernels compiled, "
                      f"{time.monotonic() - self._started:.0f} s")

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
    from posecast.solver.ik import SOLVERS

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


def warm_kernels(notice: CompileNotice | None = None) -> float:
    """Compile (or load) every kernel now; returns the seconds it took. With a notice,
    a terminal sees which step runs."""
    start = time.monotonic()
    steps = kernel_steps()
    for i, (label, run) in enumerate(steps, 1):
        if notice is not None:
            notice.step = f"[{i}/{len(steps)}] {label}: "
        run()
    if notice is not None:
        notice.close()
    return time.monotonic() - start
