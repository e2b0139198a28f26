"""A throwaway redis-server on 127.0.0.1, for `posecast demo --servers N`, `posecast bench
fanout` and the tests: Debian's redis-server, in memory only (no snapshot, no append-only
file), on a free port, gone with the ``with`` block."""

from __future__ import annotations

import shutil
import socket
import subprocess
import time
from collections.abc import Callable
from types import TracebackType

import redis

START_TIMEOUT_S = 20.0
INSTALL_HINT = "install it (Debian/Ubuntu: apt-get install redis-server)"


class RedisMissingError(RuntimeError):
    """No redis-server on this machine: one line that says how to get it."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class RedisProcess:
    """``with RedisProcess() as r: r.url`` -> redis://127.0.0.1:PORT, answering PING."""

    def __init__(self, port: int | None = None,
                 setup: Callable[[], None] | None = None) -> None:
        """``setup``: run in the child before redis-server starts (the demo pins it)."""
        self.port = port or free_port()
        self.url = f"redis://127.0.0.1:{self.port}"
        self.setup = setup
        self._proc: subprocess.Popen[bytes] | None = None

    def start(self) -> RedisProcess:
        exe = shutil.which("redis-server")
        if exe is None:
            raise RedisMissingError(f"there is no redis-server on this machine: {INSTALL_HINT}")
        self._proc = subprocess.Popen(
            [exe, "--port", str(self.port), "--bind", "127.0.0.1", "--save", "",
             "--appendonly", "no", "--protected-mode", "yes", "--loglevel", "warning"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, preexec_fn=self.setup)
        client = redis.Redis(port=self.port, socket_connect_timeout=0.5)
        t_end = time.monotonic() + START_TIMEOUT_S
        try:
            while True:
                try:
                    client.ping()
                    return self
                except redis.ConnectionError:
                    if self._proc.poll() is not None:
                        err = (self._proc.stderr.read() if self._proc.stderr else b"")
                        why = err.decode(errors="replace").strip()[:200]
                        raise RuntimeError(f"redis-server exited at start: {why}") from None
                    if time.monotonic() > t_end:
                        raise RuntimeError(f"redis-server did not answer on port "
                                           f"{self.port} within {START_TIMEOUT_S:g} s") from None
                    time.sleep(0.02)
        finally:
            client.close()

    def stop(self) -> None:
        """Gone at once (SIGKILL): what a lost Redis looks like to its clients."""
        if self._proc is not None and self._proc.poll() is None:
            self._proc.kill()
            self._proc.wait()
        self._proc = None

    def __enter__(self) -> RedisProcess:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()
