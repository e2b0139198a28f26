"""`posecast bench fanout`: how many spectators one server process serves, and how many
several serve together through Redis (``serve --redis``).

For each number of processes, a room of 4 players (90 Hz) is solved on the first and
the spectators are spread evenly over all; the count grows (x1.5, then halving the gap
between the last count that held and the first that did not) until a process no longer
holds: its probes' p99 capture-to-spectator is over the budget, or it dropped more than
1% of the frames it offered (latest wins: its sockets fell behind), twice running.

Each process runs on a core of its own, and so does the load of its spectators, at a
lower priority: every process pays for its own load alike, and a second process brings a
second core. The load is spectators that count the bytes they receive and nothing else
(``ByteCounter``): a websockets client parses each frame in Python at about the cost of
the server's send, and would measure the load generator instead of the server. A few real
spectators per process (the probes, joined last: the last of its fan-out) decode
everything and give the latency. On machines of their own, without the load beside
them, the processes would hold more.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import multiprocessing as mp
import os
import urllib.request
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import partial
from multiprocessing.connection import Connection
from typing import Any

from prometheus_client.parser import text_string_to_metric_families
from websockets.asyncio.client import connect

from posecast.client.builtin import builtin_motion_path
from posecast.client.demo import (
    ROOM,
    EmbeddedServer,
    _players_process,
    demo_cores,
    pin_to_cores,
)
from posecast.client.latency import LatencyRecorder
from posecast.client.redis_process import RedisProcess
from posecast.client.spectator import Spectator
from posecast.protocol import PROTOCOL_VERSION, Hello, encode
from posecast.server.limits import ServerLimits

BUDGET_MS = 10.0
MAX_DROPPED = 0.01  # of the frames a process offered its spectators
CONNECT_AT_ONCE = 64  # handshakes in flight while a step's spectators join
SETTLE_S = 0.5  # after the spectators joined, before measuring
# real spectators per process, joined after the load (the last of its fan-out): a p99
# of one probe's 3 s is its third worst frame, which made the steps a lottery
PROBES = 3
# the load generator yields the cores to the servers, as on machines of its own; it needs
# little (counting bytes), and one that falls behind shows as the servers' dropped frames
LOAD_NICENESS = 10
# every spectator comes from this machine's one address: the caps on connections, there
# against a flood from one host, would be what the bench measures
LIMITS = ServerLimits(connections=100_000, connections_per_address=100_000)


class ByteCounter(asyncio.Protocol):
    """A joined spectator's socket once the handshake is done: counts what comes."""

    def __init__(self) -> None:
        self.bytes = 0

    def data_received(self, data: bytes) -> None:
        self.bytes += len(data)

    def connection_lost(self, exc: Exception | None) -> None:
        pass


async def _join_counting(url: str, name: str) -> tuple[Any, ByteCounter]:
    """A spectator joined through websockets (handshake, Hello, Welcome), then its
    transport handed to a ByteCounter. Keepalive off: it lives for one step, less
    than the server's first ping."""
    ws = await connect(url, compression=None, ping_interval=None, max_size=None)
    hello = Hello(protocol_version=PROTOCOL_VERSION, role="spectator", room=ROOM,
                  display_name=name)
    await ws.send(encode(hello))
    await ws.recv()  # the welcome
    await ws.recv()  # the roster: from here every batch is offered to it
    counter = ByteCounter()
    ws.transport.set_protocol(counter)
    return ws, counter


def _load_process(pipe: Connection, url: str, count: int, core: int | None) -> None:
    """``count`` counting spectators of the server at ``url``: report when all joined,
    wait for the word, report the bytes each received and close."""
    from posecast.server.app import install_fast_loop

    install_fast_loop()
    os.nice(LOAD_NICENESS)
    if core is not None:
        os.sched_setaffinity(0, {core})

    async def main() -> None:
        limit = asyncio.Semaphore(CONNECT_AT_ONCE)

        async def one(i: int) -> tuple[Any, ByteCounter]:
            async with limit:
                return await _join_counting(url, f"load {i}")
        joined = await asyncio.gather(*(one(i) for i in range(count)),
                                      return_exceptions=True)
        ok = [j for j in joined if not isinstance(j, BaseException)]
        failed = [j for j in joined if isinstance(j, BaseException)]
        pipe.send(("joined", len(ok), str(failed[0]) if failed else ""))
        loop = asyncio.get_running_loop()
        done = asyncio.Event()
        loop.add_reader(pipe.fileno(), done.set)
        await done.wait()
        loop.remove_reader(pipe.fileno())
        pipe.recv()
        pipe.send([c.bytes for _, c in ok])
        for ws, _ in ok:
            ws.transport.abort()

    asyncio.run(main())


@contextlib.contextmanager
def _load(urls: list[str], count: int) -> Iterator[list[Connection]]:
    """One load process per server, its share of ``count``, on its server's core at a
    lower priority: each process pays for the load it serves alike, for any number of
    processes (the load of another server's spectators on a core made the two fan-outs
    cut into each other: 2 processes held fewer spectators than 1)."""
    cores = demo_cores()
    ctx = mp.get_context("spawn")
    pipes, processes = [], []
    for k, url in enumerate(urls):
        share = count // len(urls) + (1 if k < count % len(urls) else 0)
        core = cores[k % len(cores)] if len(cores) >= 2 else None
        pipe, child = ctx.Pipe()
        process = ctx.Process(target=_load_process, args=(child, url, share, core),
                              daemon=True)
        process.start()
        pipes.append(pipe)
        processes.append(process)
    try:
        yield pipes
    finally:
        for process in processes:
            process.join(30)
            if process.is_alive():
                process.kill()


def _scrape(url: str) -> dict[str, float]:
    """The frame counters of a server's /metrics."""
    http = url.replace("ws://", "http://") + "/metrics"
    with urllib.request.urlopen(http, timeout=10) as reply:
        text = reply.read().decode()
    out: dict[str, float] = {}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            if sample.name in ("posecast_frames_delivered_total",
                               "posecast_frames_dropped_total"):
                out[sample.name] = sample.value
    return out


@dataclass
class Step:
    processes: int
    spectators: int  # in all, the probes included
    p99_ms: list[float]  # each process's probe: capture to spectator
    dropped: list[float]  # each process's share of offered frames dropped
    held: bool

    def as_json(self) -> dict[str, object]:
        return {"processes": self.processes, "spectators": self.spectators,
                "capture_to_spectator_p99_ms": [round(p, 3) for p in self.p99_ms],
                "dropped": [round(d, 4) for d in self.dropped], "held": self.held}


async def _measure(urls: list[str], seconds: float) -> tuple[list[float], list[float]]:
    probes = [[Spectator(url, ROOM, f"probe {k + 1}.{j + 1}") for j in range(PROBES)]
              for k, url in enumerate(urls)]
    before = [_scrape(u) for u in urls]
    stats = await asyncio.gather(*(asyncio.gather(*(p.run(seconds=seconds) for p in ps))
                                   for ps in probes))
    after = [_scrape(u) for u in urls]
    p99 = []
    for per_process in stats:  # the probes of a process together: 3x the samples
        samples = LatencyRecorder.merged(s.latency for s in per_process).summary()
        p99.append(samples.get("capture_to_spectator", {}).get("p99", math.inf))
    dropped = []
    for b, a in zip(before, after, strict=True):
        d = {k: a.get(k, 0.0) - b.get(k, 0.0) for k in a}
        offered = d.get("posecast_frames_delivered_total", 0.0) + d.get(
            "posecast_frames_dropped_total", 0.0)
        dropped.append(d.get("posecast_frames_dropped_total", 0.0) / offered
                       if offered else 1.0)
    return p99, dropped


def _step(urls: list[str], spectators: int, seconds: float, budget_ms: float) -> Step:
    load = max(0, spectators - PROBES * len(urls))  # the probes are spectators too
    with _load(urls, load) as pipes:
        for pipe in pipes:
            if not pipe.poll(120):
                raise RuntimeError(f"{load} spectators did not join within 120 s")
            _, _, why = pipe.recv()
            if why:
                raise RuntimeError(f"not every spectator could join: {why}")
        p99, dropped = asyncio.run(_settled_measure(urls, seconds))
        for pipe in pipes:
            pipe.send("stop")
            received = pipe.recv()
            if received and min(received) == 0:  # a socket the server no longer fed
                raise RuntimeError("a load spectator received nothing during the step")
    held = all(p <= budget_ms for p in p99) and all(d <= MAX_DROPPED for d in dropped)
    return Step(len(urls), spectators, p99, dropped, held)


async def _settled_measure(urls: list[str], seconds: float) -> tuple[list[float],
                                                                     list[float]]:
    await asyncio.sleep(SETTLE_S)
    return await _measure(urls, seconds)


def _players_on(core: str, cores: tuple[int, ...], *args: Any) -> None:
    pin_to_cores(core, cores)
    _players_process(*args)


@contextlib.contextmanager
def _service(processes: int, players: int) -> Iterator[list[str]]:
    """Redis, ``processes`` servers each pinned to a core of its own (as far as the
    machine has them), and the players streaming into the first. The players, Redis and
    this process (the probes) share the first server's core whatever the number of
    processes: with them on a core of their own, one process had the machine's second
    core for its load's helpers, and two processes held no more than one."""
    cores = demo_cores()
    first = "core:0"
    with contextlib.ExitStack() as stack:
        redis_url = stack.enter_context(RedisProcess(
            setup=partial(pin_to_cores, first, cores))).url
        servers = [stack.enter_context(EmbeddedServer(
            cores=cores, redis_url=redis_url, role=f"core:{k}", limits=LIMITS))
            for k in range(processes)]
        ctx = mp.get_context("spawn")
        pipe, child = ctx.Pipe()
        process = ctx.Process(target=_players_on, args=(
            first, cores, child, servers[0].url, players, 24 * 3600.0,
            builtin_motion_path(), ()), daemon=True)
        process.start()
        pipe.send("go")
        if len(cores) >= 2:
            os.sched_setaffinity(0, {cores[0]})
        try:
            yield [s.url for s in servers]
        finally:
            if cores:
                os.sched_setaffinity(0, cores)
            process.kill()
            process.join(10)


def capacity(processes: int, players: int, start: int, seconds: float, budget_ms: float,
             progress: Callable[[Step], None], max_spectators: int) -> list[Step]:
    """The steps of one number of processes, from ``start`` spectators up."""
    steps: list[Step] = []
    with _service(processes, players) as urls:
        low, high = 0, None
        n = max(start, PROBES * processes)
        while True:
            step = _step(urls, n, seconds, budget_ms)
            steps.append(step)
            progress(step)
            if not step.held:  # a count fails twice running: a shared machine's hiccup
                step = _step(urls, n, seconds, budget_ms)  # failed single steps at random
                steps.append(step)
                progress(step)
            if step.held:
                low = n
            else:
                high = n
            if high is None:
                if n >= max_spectators:
                    break
                n = min(max_spectators, math.ceil(n * 1.5))
            elif high - low <= max(processes, high // 16):
                break
            else:
                n = (low + high) // 2
    return steps


def held_at(steps: list[Step]) -> int:
    return max((s.spectators for s in steps if s.held), default=0)


def bench_fanout(process_counts: list[int], players: int = 4, start: int = 100,
                 seconds: float = 3.0, budget_ms: float = BUDGET_MS,
                 max_spectators: int = 20000,
                 progress: Callable[[Step], None] = lambda s: None) -> dict[str, object]:
    results = []
    for processes in process_counts:
        steps = capacity(processes, players, start, seconds, budget_ms, progress,
                         max_spectators)
        results.append({"processes": processes, "spectators": held_at(steps),
                        "steps": [s.as_json() for s in steps]})
    base = results[0]["spectators"] if results else 0
    for r in results:
        r["ratio"] = round(r["spectators"] / base, 2) if base else None  # type: ignore[operator]
    return {"players": players, "budget_ms": budget_ms, "max_dropped": MAX_DROPPED,
            "results": results}


def format_fanout_table(doc: dict[str, object]) -> str:
    results = doc["results"]
    assert isinstance(results, list)
    lines = [f"spectators held (each process: probe p99 capture->spectator <= "
             f"{doc['budget_ms']} ms, <= {100 * float(doc['max_dropped']):g}% dropped), "  # type: ignore[arg-type]
             f"{doc['players']} players at 90 Hz on process 1:",
             f"{'processes':>9}  {'spectators':>10}  {'per process':>11}  {'x one':>6}"]
    for r in results:
        lines.append(f"{r['processes']:>9}  {r['spectators']:>10}  "
                     f"{r['spectators'] // r['processes']:>11}  "
                     f"{r['ratio'] if r['ratio'] is not None else '-':>6}")
    return "\n".join(lines)


def format_step(step: Step) -> str:
    p99 = ", ".join(f"{p:.1f}" for p in step.p99_ms)
    dropped = ", ".join(f"{100 * d:.1f}%" for d in step.dropped)
    return (f"{step.processes} process{'es' if step.processes > 1 else ''}, "
            f"{step.spectators:>5} spectators: p99 {p99} ms, dropped {dropped} -> "
            f"{'held' if step.held else 'not held'}")
