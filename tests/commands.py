"""A posecast command as a subprocess, read as it runs, for the tests that drive the real
command line (tests/client/cli, tests/server/test_tls.py, tests/server/test_deploy.py)."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from posecast.client.builtin import builtin_motion_path

CLIP = f"bvh:{builtin_motion_path()}"
WAIT = 120.0  # seconds for a subprocess to get somewhere (imports, kernels from cache)


class Command:
    """A posecast subprocess; its stdout and stderr are read as they come."""

    def __init__(self, *args: str, cwd: Path) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", "posecast.client.cli", *args],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True, cwd=cwd)
        self.out: list[str] = []
        self.err: list[str] = []
        self._changed = threading.Condition()
        self._readers = [threading.Thread(target=self._read, args=(stream, lines), daemon=True)
                         for stream, lines in ((self.proc.stdout, self.out),
                                               (self.proc.stderr, self.err))]
        for reader in self._readers:
            reader.start()

    def _read(self, stream: Any, lines: list[str]) -> None:
        for line in stream:
            with self._changed:
                lines.append(line)
                self._changed.notify_all()
        with self._changed:
            self._changed.notify_all()

    def wait_for(self, text: str, timeout: float = WAIT) -> str:
        """The first stderr line with ``text``; fails if the process ends without one."""
        deadline = time.monotonic() + timeout
        with self._changed:
            while True:
                for line in self.err:
                    if text in line:
                        return line
                if not self._readers[1].is_alive() or time.monotonic() > deadline:
                    pytest.fail(f"no {text!r} on stderr; got:\n{''.join(self.err)}")
                self._changed.wait(1.0)

    def finish(self, timeout: float = WAIT) -> tuple[int, str, str]:
        try:
            code = self.proc.wait(timeout)
        finally:
            self.proc.kill()
        for reader in self._readers:
            reader.join(timeout)
        return code, "".join(self.out), "".join(self.err)

    def interrupt(self) -> tuple[int, str, str]:
        self.proc.send_signal(signal.SIGINT)
        return self.finish()


def status_lines(err: str) -> list[str]:
    """stderr without the compile notice a cold kernel cache may add."""
    return [line for line in err.splitlines() if line.strip()
            and not line.startswith(("posecast: compil", " "))]


def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])
