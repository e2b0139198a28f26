#!/usr/bin/env python3
"""Where `posecast bench fanout`'s time goes at given spectator counts, on this machine.

    python scripts/fanout_at.py [--players 4] [--seconds 6] 10 300 900 1200

The bench's own service (a server process on the first core; its players, the load and
the probes on the other), one step per count as the bench takes it, but no search: at
each count it prints the probes' p50 and p99 of every stage, the server process's CPU a
second (all its threads, from /proc: 1,000 is a full core), and the room's batches,
writes carrying several batches, and avatar-frames delivered a second (its /metrics).
With the CPU at a few counts below saturation, the cost of one spectator's visit is the
slope; the probes' stages show whether a count's p99 is the server's round or the
clients' core.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import time
import urllib.request
from collections.abc import Callable
from multiprocessing.connection import Connection

from posecast.client.bench import fanout as bench

STAGES = ("capture_to_server", "server", "network_to_spectator", "capture_to_spectator")
COUNTERS = ("batches", "writes_merged", "frames_delivered")
TICKS_PER_S = os.sysconf("SC_CLK_TCK")


def _server_pid(first: int) -> int:
    """The server: this process's child pinned to core ``first`` alone."""
    me = os.getpid()
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                parent = int(f.read().rsplit(")", 1)[1].split()[1])
            if parent == me and os.sched_getaffinity(int(entry)) == {first}:
                return int(entry)
        except (OSError, ValueError):
            continue
    raise RuntimeError("no server process pinned to the first core")


def _cpu_ticks(pid: int) -> int:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return int(fields[11]) + int(fields[12])  # utime + stime, all threads


def _counters(url: str) -> dict[str, float]:
    with urllib.request.urlopen(url.replace("ws://", "http://") + "/metrics",
                                timeout=10) as reply:
        text = reply.read().decode()
    out = {}
    for name in COUNTERS:
        m = re.search(rf"^posecast_{name}_total (\S+)$", text, re.M)
        out[name] = float(m.group(1)) if m else 0.0
    return out


Measure = Callable[[list[str], list[int], list[Connection], float],
                   tuple[list[float], list[float]]]


def _measure(pid: int) -> Measure:
    """``fanout._measure`` with the server's CPU and counters, printing the stages."""
    def measure(urls: list[str], shares: list[int], probes: list[Connection],
                seconds: float) -> tuple[list[float], list[float]]:
        time.sleep(bench.SETTLE_S)
        ticks, counts, t0 = _cpu_ticks(pid), _counters(urls[0]), time.monotonic()
        for pipe in probes:
            pipe.send("go")
        time.sleep(seconds)
        for pipe in probes:
            pipe.send("stop")
        dt = time.monotonic() - t0
        cpu = (_cpu_ticks(pid) - ticks) / TICKS_PER_S / dt * 1000.0
        after = _counters(urls[0])
        rates = {k: (after[k] - counts[k]) / dt for k in COUNTERS}
        summary = bench._expect(probes[0], "the probes did not answer", 30)
        print(f"  server CPU {cpu:.0f} ms/s; a second: " + ", ".join(
            f"{k} {v:,.0f}" for k, v in rates.items()))
        for stage in STAGES:
            s = summary.get(stage, {})
            print(f"  {stage:<22} p50 {s.get('p50', float('nan')):6.2f}  "
                  f"p99 {s.get('p99', float('nan')):6.2f} ms")
        return [summary.get("capture_to_spectator", {}).get("p99", float("inf"))], [0.0]
    return measure


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("counts", type=int, nargs="+", help="spectators, each a step")
    parser.add_argument("--players", type=int, default=4)
    parser.add_argument("--seconds", type=float, default=6.0)
    args = parser.parse_args()
    if min(args.counts) < bench.PROBES or args.players < 1 or args.seconds <= 0:
        print(f"counts must be at least {bench.PROBES} (the probes), players at least 1, "
              "seconds above 0", file=sys.stderr)
        return 2
    # the bench's steps, measured by this script (its probes answer every stage)
    bench._open_files_for_sockets()
    first = min(os.sched_getaffinity(0))  # the server's core (the service pins us off it)
    with bench._service(1, args.players) as service:
        bench._measure = _measure(_server_pid(first))  # type: ignore[assignment]
        for n in args.counts:
            print(f"{n} spectators, {args.players} players:", flush=True)
            bench._step(service, n, args.seconds, None)
    return 0


if __name__ == "__main__":
    sys.exit(main())
