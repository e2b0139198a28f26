"""`posecast bench fanout`: how many spectators one server process serves, and how many
several serve together through Redis (``serve --redis``).

A room of 4 players (90 Hz) is solved on the first process. For each number of
processes K, the spectators are spread evenly over the first K, and the count grows (x1.5,
then halving the gap between the last count that held and the first that did not; the
numbers of processes take their steps in turn, on one service) until a process saturates:
its spectators no longer get the players' frames, more than 1% of them lost (superseded
before a solve, or replaced in an outbox because its sockets fell behind; latest wins, so
a saturated process loses frames rather than queueing them), twice running. Each step
reports the p99 capture-to-spectator of every process, which must stay within a budget
(25 ms, about two headset frames; ``--budget-ms``). ``--repeat`` runs it all again and
reports medians.

Each server process runs on a core of its own. Where the machine has cores no server
takes, the spectators (the load, at a lower priority, and the probes), the players and
Redis run there, as on machines of their own, and the figure is the server's (the
kernel's side of every loopback send still runs on the server's core). Where it has
none (2 processes on 2 cores), each server's spectators share its core, so that every
server pays for its own spectators alike.

The load is spectators that count the bytes they receive and nothing else
(``ByteCounter``): a websockets client parses each frame in Python at about the cost of
the server's send, and would measure the load generator instead of the server. A few
real spectators per process (the probes, joined last; the fan-out's rounds turn, so they
have each place in turn) decode everything and give the latency.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import multiprocessing as mp
import os
import resource
import statistics
import time
import urllib.request
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import partial
from multiprocessing.connection import Connection
from typing import Any

from prometheus_client.parser import text_string_to_metric_families
from websockets.asyncio.client import connect

from posecast.client.bench.demo import (
    ROOM,
    EmbeddedServer,
    _DemoSpectator,
    _players_process,
    demo_cores,
    pin_to_cores,
)
from posecast.client.bench.redis_process import RedisProcess
from posecast.client.builtin import builtin_motion_path
from posecast.client.measure.latency import LatencyRecorder
from posecast.protocol import PROTOCOL_VERSION, Hello, encode
from posecast.server.limits import ServerLimits

MAX_LOST = 0.01  # of the players' frames, at any process's spectators
# a process whose spectators get frames later than this at p99 is saturated too, lost
# frames or not: beyond about two frames of a 90 Hz headset, a viewer's interpolation
# shows the jitter (latest-wins bounds the delay, so near saturation it nears this)
BUDGET_MS = 25.0
CONNECT_AT_ONCE = 64  # handshakes in flight while a step's spectators join
SETTLE_S = 0.5  # after the spectators joined, before measuring
# real spectators per process, joined after the load (in turn at each place of the
# fan-out's rounds): a p99 of one probe's 3 s is its third worst frame, which made the
# steps a lottery
PROBES = 3
PROBES_JOIN_S = 30.0  # for a process's probes to be in the room with synced clocks
# the load generator yields the cores to the servers, as on machines of its own; it needs
# little (counting bytes), and one that falls behind shows as the servers' dropped frames
LOAD_NICENESS = 10
SWEEP_S = 0.02  # between a load process's reads of its sockets: ~2 batches each
# every spectator comes from this machine's one address: the caps on connections and
# on an address's joins (issue 27: 128 at once, then 8 a second), there against a flood
# from one host, would be what the bench measures
LIMITS = ServerLimits(connections=100_000, connections_per_address=100_000,
                      address_joins_per_s=100_000.0, address_join_burst=100_000)


class ByteCounter:
    """Joined spectators' sockets, out of the event loop once their handshakes are done:
    ``sweep`` reads each one dry, every ``SWEEP_S``. A socket that no one polls wakes no
    one when a batch lands, and one read takes several batches: on loopback the kernel
    runs the receiver's side of every send on the sender's core, so a load read frame by
    frame charged the server for waking it (as a far client never would)."""

    def __init__(self) -> None:
        self.fds: list[int] = []
        self.bytes: list[int] = []
        self._buffer = bytearray(1 << 18)

    def add(self, fd: int) -> None:
        self.fds.append(fd)
        self.bytes.append(0)

    def sweep(self) -> None:
        buffer = [self._buffer]
        for k, fd in enumerate(self.fds):
            while True:
                try:
                    n = os.readv(fd, buffer)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError:  # reset: counted as it stands
                    break
                self.bytes[k] += n
                if n < len(self._buffer):  # drained (or closed: n == 0)
                    break


async def _join_counting(url: str, name: str) -> Any:
    """A spectator joined through websockets (handshake, Hello, Welcome and roster),
    its socket then left to ``ByteCounter``. Keepalive off: it lives for one step, less
    than the server's first ping."""
    ws = await connect(url, compression=None, ping_interval=None, max_size=None)
    hello = Hello(protocol_version=PROTOCOL_VERSION, role="spectator", room=ROOM,
                  display_name=name)
    await ws.send(encode(hello))
    await ws.recv()  # the welcome
    await ws.recv()  # the roster: from here every batch is offered to it
    ws.transport.pause_reading()
    return ws


def _load_process(pipe: Connection, url: str, count: int, core: int | None) -> None:
    """``count`` counting spectators of the server at ``url``: report when all joined,
    wait for the word, report the bytes each received and over how many seconds, and
    close."""
    from posecast.server.serving import install_fast_loop

    install_fast_loop()
    os.nice(LOAD_NICENESS)
    if core is not None:
        os.sched_setaffinity(0, {core})

    async def main() -> None:
        limit = asyncio.Semaphore(CONNECT_AT_ONCE)

        async def one(i: int) -> Any:
            async with limit:
                return await _join_counting(url, f"load {i}")
        joined = await asyncio.gather(*(one(i) for i in range(count)),
                                      return_exceptions=True)
        ok = [j for j in joined if not isinstance(j, BaseException)]
        failed = [j for j in joined if isinstance(j, BaseException)]
        counter = ByteCounter()
        for ws in ok:
            counter.add(ws.transport.get_extra_info("socket").fileno())
        pipe.send(("joined", len(ok), str(failed[0]) if failed else ""))
        t_start = time.monotonic()
        while not pipe.poll(SWEEP_S):
            counter.sweep()
        pipe.recv()
        counter.sweep()
        pipe.send((counter.bytes, time.monotonic() - t_start))
        for ws in ok:
            ws.transport.abort()

    asyncio.run(main())


def _probes_process(pipe: Connection, url: str, core: int | None) -> None:
    """PROBES real spectators of the server at ``url``, on its core: report when they are
    in the room with synced clocks, measure from "go" to "stop", and send back their
    merged latency summary (every stage's percentiles, ms)."""
    if core is not None:
        os.sched_setaffinity(0, {core})

    async def main() -> None:
        probes = [_DemoSpectator(url, f"probe {j + 1}") for j in range(PROBES)]
        stop = asyncio.Event()
        tasks = [asyncio.create_task(p.run(stop=stop)) for p in probes]
        try:
            async with asyncio.timeout(PROBES_JOIN_S):
                await asyncio.gather(*(p.in_room.wait() for p in probes))
                while not all(p.session is not None and p.session.clock.synced
                              for p in probes):
                    await asyncio.sleep(0.05)
        except TimeoutError:
            pipe.send(f"probes not in the room within {PROBES_JOIN_S:g} s")
            return
        pipe.send("joined")
        await _readable(pipe)
        pipe.recv()  # go: the counters were read
        for p in probes:  # what came before the step is not its latency
            p.stats.latency = LatencyRecorder()
        await _readable(pipe)
        pipe.recv()  # stop
        pipe.send(LatencyRecorder.merged(p.stats.latency for p in probes).summary())
        stop.set()
        await asyncio.gather(*tasks, return_exceptions=True)

    asyncio.run(main())


async def _readable(pipe: Connection) -> None:
    loop = asyncio.get_running_loop()
    ready = asyncio.Event()
    loop.add_reader(pipe.fileno(), ready.set)
    try:
        await ready.wait()
    finally:
        loop.remove_reader(pipe.fileno())


@contextlib.contextmanager
def _processes(target: Callable[..., None], service: Service, *args: Any
               ) -> Iterator[list[Connection]]:
    """One process per server, running ``target(pipe, url, *args, core)`` on the core
    of that server's spectators (``Service.client_cores``)."""
    ctx = mp.get_context("spawn")
    pipes, processes = [], []
    for k, url in enumerate(service.urls):
        core = service.client_cores[k]
        pipe, child = ctx.Pipe()
        process = ctx.Process(target=target, args=(child, url, *args[k], core),
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
            if sample.name in ("posecast_frames_received_total",
                               "posecast_frames_delivered_total"):
                out[sample.name] = sample.value
    return out


def _scrape_all(urls: list[str]) -> list[dict[str, float]]:
    """Every server's counters at once: the window of each is the owner's."""
    with ThreadPoolExecutor(len(urls)) as pool:
        return list(pool.map(_scrape, urls))


@dataclass
class Step:
    processes: int
    spectators: int  # in all, the probes included
    p99_ms: list[float]  # each process's probes: capture to spectator
    lost: list[float]  # each process's share of the players' frames its spectators missed
    held: bool
    # what a load spectator received a second (median over them; None: no load ones)
    bytes_per_s_per_spectator: float | None = None

    def as_json(self) -> dict[str, object]:
        rate = self.bytes_per_s_per_spectator
        return {"processes": self.processes, "spectators": self.spectators,
                "capture_to_spectator_p99_ms": [round(p, 3) for p in self.p99_ms],
                "lost": [round(d, 4) for d in self.lost], "held": self.held,
                "bytes_per_s_per_spectator": None if rate is None else round(rate)}


def _expect(pipe: Connection, what: str, timeout: float) -> Any:
    if not pipe.poll(timeout):
        raise RuntimeError(f"{what} within {timeout:g} s")
    return pipe.recv()


def _step(service: Service, spectators: int, seconds: float, budget_ms: float | None
          ) -> Step:
    urls = service.urls
    load = max(0, spectators - PROBES * len(urls))  # the probes are spectators too
    shares = [load // len(urls) + (1 if k < load % len(urls) else 0)
              for k in range(len(urls))]
    with _processes(_load_process, service, *[(n,) for n in shares]) as loads:
        for pipe in loads:
            _, _, why = _expect(pipe, f"{load} spectators did not join", 120)
            if why:
                raise RuntimeError(f"not every spectator could join: {why}")
        with _processes(_probes_process, service, *[()] * len(urls)) as probes:
            for pipe in probes:
                if (word := _expect(pipe, "the probes did not join", 60)) != "joined":
                    raise RuntimeError(word)
            p99, lost = _measure(urls, shares, probes, seconds)
        rates: list[float] = []
        for pipe in loads:
            pipe.send("stop")
            received, seconds_counted = _expect(pipe, "a load process did not answer", 30)
            if received and min(received) == 0:  # a socket the server no longer fed
                raise RuntimeError("a load spectator received nothing during the step")
            rates += [n / seconds_counted for n in received if seconds_counted > 0]
    held = all(d <= MAX_LOST for d in lost) and (
        budget_ms is None or all(p <= budget_ms for p in p99))
    rate = statistics.median(rates) if rates else None
    return Step(len(urls), spectators, p99, lost, held, rate)


def _measure(urls: list[str], shares: list[int], probes: list[Connection],
             seconds: float) -> tuple[list[float], list[float]]:
    """Each process's p99 and its spectators' share of the players' frames lost, over
    ``seconds`` once the room settled."""
    time.sleep(SETTLE_S)
    before = _scrape_all(urls)
    for pipe in probes:
        pipe.send("go")
    time.sleep(seconds)
    for pipe in probes:
        pipe.send("stop")
    after = _scrape_all(urls)
    p99 = [float(_expect(pipe, "the probes did not answer", 30)
                 .get("capture_to_spectator", {}).get("p99", math.inf)) for pipe in probes]
    sent = after[0].get("posecast_frames_received_total", 0.0) - before[0].get(
        "posecast_frames_received_total", 0.0)  # by the players, to the owner
    lost = []
    for b, a, share in zip(before, after, shares, strict=True):
        delivered = a.get("posecast_frames_delivered_total", 0.0) - b.get(
            "posecast_frames_delivered_total", 0.0)
        expected = sent * (share + PROBES)
        lost.append(max(0.0, 1.0 - delivered / expected) if expected else 1.0)
    return p99, lost


def _players_on(core: str, cores: tuple[int, ...], *args: Any) -> None:
    pin_to_cores(core, cores)
    _players_process(*args)


@dataclass
class Service:
    urls: list[str]  # of the server processes, the owner first
    # the core each server's spectators (load and probes) run on, by server; None: any
    client_cores: list[int | None]


@dataclass
class Placement:
    """Where each process of the bench runs (``pin_to_cores`` roles and cores)."""

    client_cores: list[int | None]  # each server's spectators (load and probes), by server
    others: str  # the players and the bench itself
    redis: str


def placement(processes: int, cores: tuple[int, ...]) -> Placement:
    """Server K has core K. With cores to spare, everything else goes to them, away from
    the servers. Without, each server's spectators share its core (the load of another
    server's spectators on a core made the two fan-outs cut into each other: 2
    processes held fewer spectators than 1), the players share the first server's, and
    Redis the last one's (the far processes' relay then does not wait for the owner's
    fan-out to get the core)."""
    if len(cores) > processes:  # (processes >= 1: so two cores at least)
        spare = cores[processes:]
        return Placement([spare[k % len(spare)] for k in range(processes)],
                         f"core:{processes}", f"core:{processes}")
    clients: list[int | None] = ([cores[k % len(cores)] for k in range(processes)]
                                 if len(cores) >= 2 else [None] * processes)
    return Placement(clients, "core:0", f"core:{processes - 1}")


@contextlib.contextmanager
def _service(processes: int, players: int) -> Iterator[Service]:
    """``processes`` servers each pinned to a core of its own (as far as the machine has
    them), Redis when there are several (one process serves alone, as ``serve`` without
    ``--redis``), and the players streaming into the first (``placement``)."""
    cores = demo_cores()
    where = placement(processes, cores)
    with contextlib.ExitStack() as stack:
        redis_url = None
        if processes > 1:
            redis_url = stack.enter_context(RedisProcess(
                setup=partial(pin_to_cores, where.redis, cores))).url
        servers = [stack.enter_context(EmbeddedServer(
            cores=cores, redis_url=redis_url, role=f"core:{k}", limits=LIMITS))
            for k in range(processes)]
        ctx = mp.get_context("spawn")
        pipe, child = ctx.Pipe()
        process = ctx.Process(target=_players_on, args=(
            where.others, cores, child, servers[0].url, players, 24 * 3600.0,
            builtin_motion_path(), (), None, None), daemon=True)
        process.start()
        pipe.send("go")
        pin_to_cores(where.others, cores)
        try:
            yield Service([s.url for s in servers], where.client_cores)
        finally:
            if cores:
                os.sched_setaffinity(0, cores)
            process.kill()
            process.join(10)


@dataclass
class _Search:
    """The counts to try for one number of processes: x1.5 from the start until a count
    fails, then halving the gap between the last count that held and the first that did
    not, to within ~3%. A count fails when it fails twice running: a shared machine's
    hiccup failed single steps at random."""

    processes: int
    n: int
    max_spectators: int
    low: int = 0
    high: int | None = None
    failed_once: bool = False
    done: bool = False
    steps: list[Step] = field(default_factory=list)

    def record(self, step: Step) -> None:
        self.steps.append(step)
        if not step.held and not self.failed_once:
            self.failed_once = True  # the same count again, at its next turn
            return
        self.failed_once = False
        if step.held:
            self.low = self.n
        else:
            self.high = self.n
        if self.high is None:
            if self.n >= self.max_spectators:
                self.done = True
            self.n = min(self.max_spectators, math.ceil(self.n * 1.5))
        elif self.high - self.low <= max(self.processes, self.high // 32):
            self.done = True
        else:
            self.n = (self.low + self.high) // 2


def capacities(process_counts: list[int], players: int, start: int, seconds: float,
               budget_ms: float | None, progress: Callable[[Step], None],
               max_spectators: int) -> list[list[Step]]:
    """The steps of each number of processes, taken in turn on one service of as many
    processes as the largest number (K processes: the first K serve the spectators, the
    others have none), so that a change in the machine's speed during the run (a shared
    VM's neighbours) falls on every number alike and not on the ratio between them."""
    searches = [_Search(k, max(start, PROBES * k), max_spectators) for k in process_counts]
    with _service(max(process_counts), players) as service:
        while not all(s.done for s in searches):
            for search in searches:
                if search.done:
                    continue
                first = Service(service.urls[:search.processes],
                                service.client_cores[:search.processes])
                step = _step(first, search.n, seconds, budget_ms)
                search.record(step)
                progress(step)
    return [s.steps for s in searches]


def held_step(steps: list[Step]) -> Step | None:
    """The step of the most spectators that held."""
    held = [s for s in steps if s.held]
    return max(held, key=lambda s: s.spectators) if held else None


def _open_files_for_sockets() -> None:
    """Each spectator is a socket in a server and one in a load process: raise the soft
    limit on open files to the hard one (often 1024 against a hard 4096 or more)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != resource.RLIM_INFINITY and (hard == resource.RLIM_INFINITY or soft < hard):
        resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))


def bench_fanout(process_counts: list[int], players: int = 4, start: int = 200,
                 seconds: float = 4.0, budget_ms: float | None = BUDGET_MS,
                 max_spectators: int = 20000, repeat: int = 1,
                 progress: Callable[[Step], None] = lambda s: None) -> dict[str, object]:
    """``repeat`` whole runs: each number of processes gets the median of its runs'
    counts, and the ratio is the median of each run's own ratio (a run's numbers of
    processes measured in the same minutes). One run's count swings by a third on a
    shared 2-core VM; a median of several does not follow one bad run."""
    _open_files_for_sockets()
    runs = [capacities(process_counts, players, start, seconds, budget_ms, progress,
                       max_spectators) for _ in range(repeat)]
    counts = [[_held_count(steps) for steps in run] for run in runs]  # [run][processes]
    ratios = [[round(c / run[0], 2) if run[0] else None for c in run] for run in counts]
    results: list[dict[str, Any]] = []
    for k, processes in enumerate(process_counts):
        per_run = [run[k] for run in counts]
        median = statistics.median_low(per_run)
        best = held_step(runs[per_run.index(median)][k])  # of the median run
        run_ratios = [x for r in ratios if (x := r[k]) is not None]
        results.append({
            "processes": processes, "spectators": median, "runs": per_run,
            "ratio": round(statistics.median(run_ratios), 2) if run_ratios else None,
            "ratios": [r[k] for r in ratios],
            "capture_to_spectator_p99_ms": ([round(p, 3) for p in best.p99_ms]
                                            if best else None),
            # what each of them received a second at that count (the load spectators')
            "bytes_per_s_per_spectator": (
                None if best is None or best.bytes_per_s_per_spectator is None
                else round(best.bytes_per_s_per_spectator)),
            "steps": [[s.as_json() for s in run[k]] for run in runs]})
    return {"players": players, "budget_ms": budget_ms, "max_lost": MAX_LOST,
            "repeat": repeat, "results": results}


def _held_count(steps: list[Step]) -> int:
    best = held_step(steps)
    return best.spectators if best else 0


def format_fanout_table(doc: dict[str, Any]) -> str:
    budget = doc["budget_ms"]
    runs = doc["repeat"]
    lines = [f"spectators served before a process saturates (its spectators miss more "
             f"than {100 * doc['max_lost']:g}% of the players' frames"
             + (f", or its p99 capture->spectator is over {budget:g} ms" if budget else "")
             + f"), {doc['players']} players at 90 Hz on process 1"
             + (f"; medians of {runs} runs" if runs > 1 else "") + ":",
             f"{'processes':>9}  {'spectators':>10}  {'per process':>11}  {'x one':>6}  "
             f"{'p99 ms (each process)':>21}  {'Mbit/s each':>11}"
             + ("  runs (x one)" if runs > 1 else "")]
    for r in doc["results"]:
        p99 = r["capture_to_spectator_p99_ms"]
        rate = r.get("bytes_per_s_per_spectator")
        line = (f"{r['processes']:>9}  {r['spectators']:>10}  "
                f"{r['spectators'] // r['processes']:>11}  "
                f"{r['ratio'] if r['ratio'] is not None else '-':>6}  "
                f"{', '.join(f'{p:.1f}' for p in p99) if p99 else '-':>21}  "
                f"{f'{rate * 8 / 1e6:.2f}' if rate is not None else '-':>11}")
        if runs > 1:
            line += "  " + ", ".join(f"{c} ({x if x is not None else '-'})"
                                     for c, x in zip(r["runs"], r["ratios"], strict=True))
        lines.append(line)
    return "\n".join(lines)


def format_step(step: Step) -> str:
    p99 = ", ".join(f"{p:.1f}" for p in step.p99_ms)
    lost = ", ".join(f"{100 * d:.1f}%" for d in step.lost)
    rate = step.bytes_per_s_per_spectator
    per = f", {rate * 8 / 1e6:.2f} Mbit/s each" if rate is not None else ""
    return (f"{step.processes} process{'es' if step.processes > 1 else ''}, "
            f"{step.spectators:>5} spectators: p99 {p99} ms, lost {lost}{per} -> "
            f"{'held' if step.held else 'not held'}")
