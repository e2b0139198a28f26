"""`posecast bench startup`: how long a person waits for the first commands after set-up.

Each command runs as a fresh process, as a person would type it: `posecast --version`
(Python and the package's imports), `posecast serve` until it accepts a connection, and
`posecast eval` of the built-in clip to its last line (so its scoring started earlier).
A run that had to compile kernels is flagged: `make setup` should have left none."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time

import numpy as np

from posecast.client.jit import NOTICE

COMMAND = [sys.executable, "-m", "posecast.client.cli"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _accepts(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def time_serve(timeout: float = 120.0) -> tuple[float, bool]:
    """Seconds from starting `posecast serve` to its port accepting a connection."""
    port = _free_port()
    start = time.perf_counter()
    proc = subprocess.Popen([*COMMAND, "serve", "--port", str(port)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        while not _accepts(port):
            if proc.poll() is not None:
                raise RuntimeError(f"posecast serve exited: {proc.stderr.read()[-500:]}"
                                   if proc.stderr else "posecast serve exited")
            if time.perf_counter() - start > timeout:
                raise RuntimeError(f"posecast serve did not listen within {timeout:.0f} s")
            time.sleep(0.005)
        elapsed = time.perf_counter() - start
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    return elapsed, NOTICE in err


def time_command(args: list[str]) -> tuple[float, bool]:
    """Seconds a command takes to finish, and whether it compiled anything."""
    start = time.perf_counter()
    proc = subprocess.run([*COMMAND, *args], capture_output=True, text=True, check=False)
    elapsed = time.perf_counter() - start
    if proc.returncode != 0:
        raise RuntimeError(f"posecast {' '.join(args)} failed: {proc.stderr.strip()[-500:]}")
    return elapsed, NOTICE in proc.stderr


def bench_startup(runs: int, progress: bool = True) -> dict[str, object]:
    cases: list[tuple[str, object]] = [
        ("posecast --version", lambda: time_command(["--version"])),
        ("posecast play --help", lambda: time_command(["play", "--help"])),
        ("posecast serve (listening)", time_serve),
        ("posecast eval (built-in clip, done)", lambda: time_command(["eval"])),
    ]
    results = []
    live = sys.stderr.isatty()  # to a pipe or a log: whole lines, never \r-joined fragments
    for label, run in cases:
        times, compiled = [], False
        for i in range(runs):
            if progress:
                step = f"{label}: run {i + 1}/{runs}"
                sys.stderr.write(f"\r{step}" if live else f"{step}\n")
                sys.stderr.flush()
            elapsed, did_compile = run()  # type: ignore[operator]
            times.append(elapsed)
            compiled |= did_compile
        results.append({"command": label, "runs": runs,
                        "seconds_p50": round(float(np.median(times)), 3),
                        "seconds_max": round(float(max(times)), 3), "compiled": compiled})
    if progress and live:
        sys.stderr.write("\r" + " " * 60 + "\r")
    return {"cpus": os.cpu_count(), "results": results}


def format_startup_table(doc: dict[str, object]) -> str:
    rows = doc["results"]
    width = max(len(str(r["command"])) for r in rows)  # type: ignore[attr-defined]
    lines = [f"{'command':{width}s}  p50 s   max s"]
    for r in rows:  # type: ignore[attr-defined]
        flag = "  (compiled kernels: run `posecast warm`)" if r["compiled"] else ""
        lines.append(f"{r['command']:{width}s}  {r['seconds_p50']:5.2f}  {r['seconds_max']:6.2f}"
                     f"{flag}")
    return "\n".join(lines)
