"""A network on loopback: a TCP proxy that delays, jitters and stalls what it forwards.

Over a real link a spectator sees frames late and unevenly; this proxy makes that happen
on 127.0.0.1 so that tests and ``posecast demo --network`` can measure it. Each chunk read
from one side is written to the other after a delay drawn uniformly from DELAY +- JITTER
(netem's default distribution), never before the chunk ahead of it: TCP delivers in order,
so a late chunk holds up the ones behind it. Now and then (a Poisson process, on average
once per EVERY) the next chunk is held a further HOLD, as when a segment is lost and sent
again after the retransmission timeout (Linux's minimum RTO is 200 ms); everything behind
it arrives in one burst.

The spec, as the user types it: ``40ms+-10ms``, ``40ms``, ``40ms+-10ms,stall=200ms/5s``,
optionally ``,seed=N``. ``LinkModel`` is the pure part (when a chunk read at t is due);
``NetworkProxy`` the asyncio part; ``ProxyProcess`` runs one in a process of its own.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import multiprocessing as mp
import random
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing.connection import Connection

CHUNK_BYTES = 65536
MAX_DELAY_S = 10.0  # a longer one-way delay is a typo, not a network
LINGER_S = 10.0  # after one direction ended, how long the other may go on (half-close)
_UNITS = {"ms": 1e-3, "s": 1.0}
_TIME = r"(\d+(?:\.\d*)?|\.\d+)(ms|s)"
SPEC_FORM = "DELAY[+-JITTER][,stall=HOLD/EVERY][,seed=N], e.g. 40ms+-10ms,stall=200ms/5s"


@dataclass(frozen=True)
class NetworkSpec:
    """One direction of a link, seconds; each direction of each connection draws its own."""

    delay: float
    jitter: float = 0.0
    stall_hold: float = 0.0  # 0: no stalls
    stall_every: float = math.inf  # mean time between stalls
    seed: int = 0
    text: str = ""

    def __str__(self) -> str:
        return self.text or f"{self.delay * 1e3:g}ms+-{self.jitter * 1e3:g}ms"


def _seconds(value: str, unit: str) -> float:
    return float(value) * _UNITS[unit]


def parse_network_spec(text: str) -> NetworkSpec:
    """The spec of ``text`` (see the module docstring); ValueError says what is wrong."""
    parts = text.strip().split(",")
    head = re.fullmatch(_TIME + r"(?:\+-" + _TIME + r")?", parts[0].strip())
    if head is None:
        raise ValueError(f"must be {SPEC_FORM}; got {text!r}")
    delay = _seconds(head.group(1), head.group(2))
    jitter = _seconds(head.group(3), head.group(4)) if head.group(3) else 0.0
    if delay > MAX_DELAY_S:
        raise ValueError(f"delay must be at most {MAX_DELAY_S:g}s, got {text!r}")
    if jitter > delay:
        raise ValueError(f"jitter must not exceed the delay (no chunk arrives before it "
                         f"is sent), got {text!r}")
    hold, every, seed = 0.0, math.inf, 0
    for part in (p.strip() for p in parts[1:]):
        stall = re.fullmatch(r"stall=" + _TIME + "/" + _TIME, part)
        seeded = re.fullmatch(r"seed=(\d{1,9})", part)
        if stall is not None:
            hold = _seconds(stall.group(1), stall.group(2))
            every = _seconds(stall.group(3), stall.group(4))
            if not (0.0 < hold <= MAX_DELAY_S and every > 0.0):
                raise ValueError(f"stall must be HOLD/EVERY with 0 < HOLD <= "
                                 f"{MAX_DELAY_S:g}s and EVERY > 0, got {part!r}")
        elif seeded is not None:
            seed = int(seeded.group(1))
        else:
            raise ValueError(f"must be {SPEC_FORM}; {part!r} is neither stall=HOLD/EVERY "
                             "nor seed=N")
    return NetworkSpec(delay, jitter, hold, every, seed, text.strip())


@dataclass
class LinkStats:
    chunks: int = 0
    bytes: int = 0
    stalls: int = 0
    delays: list[float] = field(default_factory=list)  # release - read, seconds


class LinkModel:
    """When each chunk of one direction is due: pure, seeded, in the caller's time."""

    def __init__(self, spec: NetworkSpec, rng: random.Random, t0: float,
                 stats: LinkStats | None = None) -> None:
        self.spec = spec
        self.rng = rng
        self.stats = stats if stats is not None else LinkStats()
        self._last = -math.inf
        self._next_stall = t0 + self._gap()

    def _gap(self) -> float:
        if self.spec.stall_hold <= 0.0 or not math.isfinite(self.spec.stall_every):
            return math.inf
        return self.rng.expovariate(1.0 / self.spec.stall_every)

    def release_time(self, t_read: float, size: int = 0) -> float:
        spec = self.spec
        due = t_read + spec.delay + self.rng.uniform(-spec.jitter, spec.jitter)
        if t_read >= self._next_stall:  # this chunk was "lost": resent a hold later
            due += spec.stall_hold
            self.stats.stalls += 1
            while self._next_stall <= t_read:
                self._next_stall += self._gap()
        due = max(due, self._last)  # in order, as TCP delivers
        self._last = due
        self.stats.chunks += 1
        self.stats.bytes += size
        self.stats.delays.append(due - t_read)
        return due


class NetworkProxy:
    """Listens on ``host``: each connection is forwarded to the target, both directions
    through a ``LinkModel`` of ``spec``. ``async with`` starts and stops it."""

    def __init__(self, target_host: str, target_port: int, spec: NetworkSpec,
                 host: str = "127.0.0.1", port: int = 0, linger: float = LINGER_S) -> None:
        self.target = (target_host, target_port)
        self.spec = spec
        self.host, self.port = host, port
        self.linger = linger
        self.upstream = LinkStats()  # client -> target, summed over connections
        self.downstream = LinkStats()  # target -> client
        self.connections = 0
        self._server: asyncio.Server | None = None
        self._handlers: set[asyncio.Task[None]] = set()

    async def start(self) -> int:
        self._server = await asyncio.start_server(self._accept, self.host, self.port)
        self.port = self._server.sockets[0].getsockname()[1]
        return self.port

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            for task in list(self._handlers):
                task.cancel()
            await asyncio.gather(*self._handlers, return_exceptions=True)
            await self._server.wait_closed()
            self._server = None

    async def __aenter__(self) -> NetworkProxy:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.get_running_loop().create_task(self._connection(reader, writer))
        self._handlers.add(task)
        task.add_done_callback(self._handlers.discard)

    async def _connection(self, client_r: asyncio.StreamReader,
                          client_w: asyncio.StreamWriter) -> None:
        n = self.connections
        self.connections += 1
        try:
            target_r, target_w = await asyncio.open_connection(*self.target)
        except OSError:
            client_w.close()  # the target refuses: so does the "network"
            return
        t0 = asyncio.get_running_loop().time()
        seed = self.spec.seed * 1_000_003 + 2 * n  # each direction its own draws
        pipes = [asyncio.create_task(_pipe(client_r, target_w, LinkModel(
                     self.spec, random.Random(seed), t0, self.upstream))),
                 asyncio.create_task(_pipe(target_r, client_w, LinkModel(
                     self.spec, random.Random(seed + 1), t0, self.downstream)))]
        try:
            done, pending = await asyncio.wait(pipes, return_when=asyncio.FIRST_COMPLETED)
            # a direction that ended with an error (a reset): the connection is gone;
            # one that ended cleanly (EOF, passed on): the other may still finish
            if all(t.exception() is None for t in done) and pending:
                await asyncio.wait(pending, timeout=self.linger)
        finally:
            for task in pipes:
                task.cancel()
            await asyncio.gather(*pipes, return_exceptions=True)
            for w in (client_w, target_w):
                w.close()


async def _pipe(reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                link: LinkModel) -> None:
    """Read chunks as they come, write each at its release time; pass the EOF on after
    the last one (a half-close: the other direction goes on)."""
    loop = asyncio.get_running_loop()
    queue: asyncio.Queue[tuple[float, bytes] | None] = asyncio.Queue()

    async def deliver() -> None:
        while (item := await queue.get()) is not None:
            due, data = item
            wait = due - loop.time()
            if wait > 0.0:
                await asyncio.sleep(wait)
            writer.write(data)
            await writer.drain()
        if writer.can_write_eof():
            writer.write_eof()

    sender = asyncio.create_task(deliver())
    try:
        while data := await reader.read(CHUNK_BYTES):
            queue.put_nowait((link.release_time(loop.time(), len(data)), data))
            if sender.done():  # the other side went away: stop reading for it
                break
        queue.put_nowait(None)
        await sender
    finally:
        sender.cancel()


def _proxy_process(pipe: Connection, port: int, spec: NetworkSpec,
                   setup: Callable[[], None] | None) -> None:
    if setup is not None:
        setup()

    async def main() -> dict[str, object]:
        stop = asyncio.Event()
        asyncio.get_running_loop().add_reader(pipe.fileno(), stop.set)
        async with NetworkProxy("127.0.0.1", port, spec) as proxy:
            pipe.send(proxy.port)
            await stop.wait()
        return {"connections": proxy.connections,
                "upstream": _summary(proxy.upstream),
                "downstream": _summary(proxy.downstream)}

    pipe.send(asyncio.run(main()))


def _summary(stats: LinkStats) -> dict[str, object]:
    delays = sorted(stats.delays)
    p50 = delays[len(delays) // 2] * 1e3 if delays else 0.0
    return {"chunks": stats.chunks, "bytes": stats.bytes, "stalls": stats.stalls,
            "delay_ms_p50": round(p50, 2)}


class ProxyProcess:
    """A ``NetworkProxy`` to 127.0.0.1:``port`` in a process of its own for the length of
    a ``with`` block: its timers then fire on time whatever the clients' loop is doing.
    ``setup`` runs first in the child (a picklable function: pinning it to cores)."""

    def __init__(self, port: int, spec: NetworkSpec,
                 setup: Callable[[], None] | None = None) -> None:
        ctx = mp.get_context("spawn")
        self._pipe, child = ctx.Pipe()
        self._process = ctx.Process(target=_proxy_process, args=(child, port, spec, setup),
                                    daemon=True)
        self.port = 0
        self.stats: dict[str, object] = {}

    @property
    def url(self) -> str:
        return f"ws://127.0.0.1:{self.port}"

    def __enter__(self) -> ProxyProcess:
        self._process.start()
        if not self._pipe.poll(60):
            self._process.kill()
            raise RuntimeError("the network emulator did not start within 60 s")
        self.port = int(self._pipe.recv())
        return self

    def __exit__(self, *exc: object) -> None:
        with contextlib.suppress(OSError):  # it is gone already: nothing to stop
            self._pipe.send("stop")
        with contextlib.suppress(EOFError, OSError):  # gone: no counts
            if self._pipe.poll(30):
                self.stats = self._pipe.recv()
        self._process.join(10)
        if self._process.is_alive():
            self._process.kill()
