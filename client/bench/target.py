"""A server process under measurement, for `posecast bench soak` and `bench hostile`.

Like the demo's ``EmbeddedServer`` (a fresh process on loopback), but it answers
"metrics" on its pipe while it serves, so that a bench can sample its counters over
time, and its RSS and open file descriptors are read from /proc by its pid.
"""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing as mp
import os
from multiprocessing.connection import Connection
from pathlib import Path

START_TIMEOUT = 60.0
STOP_TIMEOUT = 30.0
METRICS_TIMEOUT = 10.0


def _serve(pipe: Connection, solver: str) -> None:
    from posecast.server.app import Session
    from posecast.server.serving import install_fast_loop, run_server

    install_fast_loop()

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        session = Session(solver=solver)

        def on_message() -> None:  # "metrics": the counters now; anything else: stop
            try:
                if pipe.recv() == "metrics":
                    pipe.send(session.metrics.as_json())
                    return
            except (EOFError, OSError):  # the parent is gone
                pass
            loop.remove_reader(pipe.fileno())
            stop.set()

        loop.add_reader(pipe.fileno(), on_message)
        await run_server("127.0.0.1", 0, session, stop, ready=pipe.send,
                         drain_timeout=2.0)
        loop.remove_reader(pipe.fileno())
        with contextlib.suppress(OSError):
            pipe.send(session.metrics.as_json())

    asyncio.run(main())


class TargetServer:
    """``with TargetServer() as server``: a server process on a free port of loopback."""

    def __init__(self, solver: str = "analytic") -> None:
        ctx = mp.get_context("spawn")  # a fresh interpreter: no inherited event loop
        self._pipe, child = ctx.Pipe()
        self._process = ctx.Process(target=_serve, args=(child, solver), daemon=True)
        self.port = 0
        self.final_metrics: dict[str, object] = {}

    def __enter__(self) -> TargetServer:
        self._process.start()
        if not self._pipe.poll(START_TIMEOUT):
            self._process.kill()
            raise RuntimeError(f"the server did not start within {START_TIMEOUT:g} s")
        self.port = int(self._pipe.recv())
        return self

    def __exit__(self, *exc: object) -> None:
        if self._process.is_alive():
            try:
                self._pipe.send("stop")
                if self._pipe.poll(STOP_TIMEOUT):
                    self.final_metrics = self._pipe.recv()
            except (OSError, EOFError):
                pass
        self._process.join(10)
        if self._process.is_alive():
            self._process.kill()
            self._process.join(5)

    @property
    def url(self) -> str:
        return f"ws://127.0.0.1:{self.port}"

    @property
    def pid(self) -> int:
        assert self._process.pid is not None
        return self._process.pid

    @property
    def alive(self) -> bool:
        return self._process.is_alive()

    def metrics(self) -> dict[str, object]:
        """The server's counters now (``Metrics.as_json``); {} if it does not answer."""
        if not self._process.is_alive():
            return {}
        self._pipe.send("metrics")
        if not self._pipe.poll(METRICS_TIMEOUT):
            return {}
        reply = self._pipe.recv()
        return reply if isinstance(reply, dict) else {}

    def rss_mb(self) -> float:
        return rss_mb(self.pid)

    def open_fds(self) -> int:
        return open_fds(self.pid)

    def cpu_s(self) -> float:
        return cpu_s(self.pid)


def rss_mb(pid: int) -> float:
    """Resident set size of a process in MB (VmRSS of /proc/PID/status); NaN if gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def open_fds(pid: int) -> int:
    """Open file descriptors of a process (entries of /proc/PID/fd); -1 if unknown."""
    try:
        return len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return -1


def cpu_s(pid: int) -> float:
    """CPU time a process has used, user and system, in seconds (utime + stime of
    /proc/PID/stat); NaN if gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return float("nan")
    fields = text[text.rindex(")") + 2:].split()  # after the command, which may hold spaces
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
