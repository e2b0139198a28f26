"""The network emulator (client/bench/network.py): its spec, its link model, and the proxy over
real sockets on 127.0.0.1: it delays by the asked amount, keeps byte order, stalls as
asked and closes both sides when one closes; the CLI refuses a bad spec in one line."""

from __future__ import annotations

import asyncio
import os
import random
import socket
import statistics
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Iterator
from contextlib import asynccontextmanager, contextmanager

import pytest

from posecast.client.bench.network import (
    LinkModel,
    NetworkProxy,
    NetworkSpec,
    parse_network_spec,
)

WAIT = 30.0  # generous: a loaded machine may be slow to schedule anything


# --------------------------------------------------------------------------- the spec
@pytest.mark.parametrize(("text", "spec"), [
    ("40ms+-10ms", NetworkSpec(0.040, 0.010, text="40ms+-10ms")),
    ("40ms", NetworkSpec(0.040, text="40ms")),
    ("0.1s+-20ms", NetworkSpec(0.1, 0.020, text="0.1s+-20ms")),
    ("40ms+-10ms,stall=200ms/5s", NetworkSpec(0.040, 0.010, 0.2, 5.0,
                                              text="40ms+-10ms,stall=200ms/5s")),
    ("5ms,seed=7", NetworkSpec(0.005, seed=7, text="5ms,seed=7")),
])
def test_specs_parse(text: str, spec: NetworkSpec) -> None:
    got = parse_network_spec(text)
    for name in ("delay", "jitter", "stall_hold", "stall_every", "seed", "text"):
        assert getattr(got, name) == pytest.approx(getattr(spec, name)), name
    assert str(got) == text


@pytest.mark.parametrize(("text", "why"), [
    ("40", "must be"), ("fast", "must be"), ("-5ms", "must be"), ("40ms+-", "must be"),
    ("40ms+-50ms", "jitter must not exceed"), ("11s", "at most"),
    ("40ms,stall=0ms/5s", "stall must"), ("40ms,stall=200ms/0s", "stall must"),
    ("40ms,loss=1%", "neither"), ("40ms,stall=200ms", "neither"),
])
def test_bad_specs_say_what_is_wrong(text: str, why: str) -> None:
    with pytest.raises(ValueError, match=why):
        parse_network_spec(text)


def test_a_bad_spec_is_one_line_and_exit_2() -> None:
    done = subprocess.run([sys.executable, "-m", "posecast.client.cli", "demo", "--network",
                           "40ms+-50ms"], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "PYTHONWARNINGS": "ignore"})
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith("posecast demo: --network") and "jitter" in lines[0]


# --------------------------------------------------------------------------- the model
def test_the_link_model_delays_within_the_range_in_order() -> None:
    link = LinkModel(parse_network_spec("40ms+-10ms"), random.Random(1), t0=0.0)
    reads = [i * 0.002 for i in range(5000)]  # 500 chunks a second: many overtake
    due = [link.release_time(t) for t in reads]
    assert due == sorted(due)  # never one before the chunk ahead of it
    delays = [d - t for d, t in zip(due, reads, strict=True)]
    assert min(delays) >= 0.030 - 1e-12
    # a chunk waits only behind a later-drawn one ahead of it: never past its maximum
    assert max(delays) <= 0.050 + 1e-12
    sparse = LinkModel(parse_network_spec("40ms+-10ms"), random.Random(2), t0=0.0)
    apart = [sparse.release_time(i * 0.1) - i * 0.1 for i in range(2000)]
    assert statistics.median(apart) == pytest.approx(0.040, abs=0.001)  # uniform, centred


def test_the_link_model_stalls_about_as_often_as_asked() -> None:
    link = LinkModel(parse_network_spec("10ms,stall=200ms/2s"), random.Random(3), t0=0.0)
    due = [link.release_time(i / 90.0) for i in range(90 * 600)]  # ten minutes at 90 Hz
    assert 300 * 0.8 < link.stats.stalls < 300 * 1.2  # one per 2 s on average
    late = [d - i / 90.0 for i, d in enumerate(due)]
    assert max(late) == pytest.approx(0.210, abs=1e-9)  # the held chunk itself
    # the chunks read during the 200 ms hold (18 at 90 Hz) come out with the held one,
    # as after a retransmission (fewer when two stalls overlap)
    assert sum(1 for x in late if x > 0.02) > 12 * link.stats.stalls


# --------------------------------------------------------------------------- real sockets
class Sink:
    """A TCP server that timestamps each 8-byte message it reads and can echo it back."""

    def __init__(self, echo: bool = False) -> None:
        self.echo = echo
        self.arrivals: dict[int, float] = {}
        self.received = bytearray()
        self.eof = asyncio.Event()
        self.writers: list[asyncio.StreamWriter] = []

    async def handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.writers.append(writer)
        pending = b""
        while data := await reader.read(65536):
            t = time.perf_counter()
            self.received += data
            if self.echo:
                writer.write(data)
            pending += data
            while len(pending) >= 8:
                self.arrivals[int.from_bytes(pending[:8], "big")] = t
                pending = pending[8:]
        self.eof.set()
        writer.close()


@asynccontextmanager
async def proxied(spec: str, sink: Sink) -> AsyncIterator[NetworkProxy]:
    server = await asyncio.start_server(sink.handle, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        async with NetworkProxy("127.0.0.1", port, parse_network_spec(spec)) as proxy:
            yield proxy
    finally:
        server.close()


async def _send_spaced(port: int, count: int, gap: float) -> dict[int, float]:
    _, writer = await asyncio.open_connection("127.0.0.1", port)
    sent = {}
    for i in range(count):
        sent[i] = time.perf_counter()
        writer.write(i.to_bytes(8, "big"))
        await writer.drain()
        await asyncio.sleep(gap)
    await asyncio.sleep(0.3)
    writer.close()
    return sent


def test_the_proxy_delays_by_the_asked_amount() -> None:
    async def run() -> tuple[list[float], list[float]]:
        sink = Sink()
        async with proxied("40ms+-10ms,seed=5", sink) as proxy:
            sent = await _send_spaced(proxy.port, 150, 0.02)
            await asyncio.wait_for(sink.eof.wait(), WAIT)
            model = proxy.upstream.delays
        return [sink.arrivals[i] - sent[i] for i in sent], model

    measured, model = asyncio.run(run())
    assert len(measured) == 150
    median = statistics.median(measured)
    # the target is 40 ms; a few ms for the loop's timers and a busy machine
    assert 0.036 <= median <= 0.050, median
    # spread as drawn: no message before 30 ms (a loaded machine only adds)
    assert min(measured) >= 0.030 - 0.001, min(measured)
    assert statistics.median(model) == pytest.approx(0.040, abs=0.004)


def test_the_proxy_keeps_every_byte_in_order_both_ways() -> None:
    payload = random.Random(9).randbytes(1_500_000)

    async def run() -> bytes:
        sink = Sink(echo=True)
        async with proxied("20ms+-15ms", sink) as proxy:
            reader, writer = await asyncio.open_connection("127.0.0.1", proxy.port)
            back = bytearray()

            async def read_back() -> None:
                while len(back) < len(payload):
                    data = await reader.read(65536)
                    if not data:
                        break
                    back.extend(data)

            reading = asyncio.create_task(read_back())
            rng = random.Random(4)
            i = 0
            while i < len(payload):  # writes of uneven sizes, some apart in time
                n = rng.randint(1, 40_000)
                writer.write(payload[i:i + n])
                i += n
                await writer.drain()
                if rng.random() < 0.2:
                    await asyncio.sleep(0.003)
            await asyncio.wait_for(reading, WAIT)
            writer.close()
            assert bytes(sink.received) == payload  # upstream, as sent
            return bytes(back)

    assert asyncio.run(run()) == payload  # and back down


def test_the_proxy_stalls_as_asked() -> None:
    async def run(spec: str) -> tuple[list[float], int]:
        sink = Sink()
        async with proxied(spec, sink) as proxy:
            sent = await _send_spaced(proxy.port, 200, 0.015)
            await asyncio.wait_for(sink.eof.wait(), WAIT)
            stalls = proxy.upstream.stalls
        return [sink.arrivals[i] - sent[i] for i in sent], stalls

    plain, none = asyncio.run(run("10ms,seed=2"))
    assert none == 0
    stalled, stalls = asyncio.run(run("10ms,stall=300ms/1s,seed=2"))
    assert stalls >= 1  # ~3 s of sending, one stall a second on average
    # each stall holds a chunk 300 ms more, and those behind it wait with it
    held = [d for d in stalled if d >= 0.25]
    assert len(held) >= stalls
    assert max(stalled) >= 0.30
    # the same link without stalls holds nothing that long (generous: a loaded machine)
    assert max(plain) < 0.25 and statistics.median(plain) < 0.05


def test_the_proxy_closes_both_sides_when_one_closes() -> None:
    async def client_closes() -> None:
        sink = Sink(echo=True)
        async with proxied("5ms", sink) as proxy:
            reader, writer = await asyncio.open_connection("127.0.0.1", proxy.port)
            writer.write(b"12345678")
            assert await asyncio.wait_for(reader.readexactly(8), WAIT) == b"12345678"
            writer.close()  # the client goes: the server sees its end after the data
            await asyncio.wait_for(sink.eof.wait(), WAIT)
            assert bytes(sink.received) == b"12345678"

    async def server_closes() -> None:
        sink = Sink()
        async with proxied("5ms", sink) as proxy:
            reader, writer = await asyncio.open_connection("127.0.0.1", proxy.port)
            writer.write(b"abcdefgh")
            await writer.drain()
            while not sink.writers:
                await asyncio.sleep(0.01)
            sink.writers[0].write(b"last words")
            sink.writers[0].close()  # the server goes: the client reads the rest, then EOF
            assert await asyncio.wait_for(reader.read(), WAIT) == b"last words"
            writer.close()

    async def target_refuses() -> None:
        with socketless_port() as port:
            async with NetworkProxy("127.0.0.1", port, parse_network_spec("5ms")) as proxy:
                reader, writer = await asyncio.open_connection("127.0.0.1", proxy.port)
                assert await asyncio.wait_for(reader.read(), WAIT) == b""  # closed at once
                writer.close()

    asyncio.run(client_closes())
    asyncio.run(server_closes())
    asyncio.run(target_refuses())


@contextmanager
def socketless_port() -> Iterator[int]:
    """A port on 127.0.0.1 that nothing listens on (bound, never listened)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        yield sock.getsockname()[1]


def test_the_viewer_s_buffer_delay_grows_with_the_jitter_it_measures() -> None:
    """Frames at 90 Hz through the proxy into a viewer's snapshot buffer: a jittery link
    makes the buffer hold frames longer (delay = jitter p95 + one interval)."""
    import numpy as np

    from posecast.client.viewer.interpolation import Snapshot, SnapshotBuffer

    async def through(spec: str) -> float:
        buffer = SnapshotBuffer()
        done = asyncio.Event()

        async def viewer(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            while data := await reader.read(16):
                if len(data) < 16:  # a frame split by the link: read the rest
                    data += await reader.readexactly(16 - len(data))
                for k in range(0, len(data), 16):  # several may come in one chunk
                    seq = int.from_bytes(data[k:k + 8], "big")
                    t_capture = float(np.frombuffer(data[k + 8:k + 16], ">f8")[0])
                    buffer.add(Snapshot(seq, t_capture, time.perf_counter(),
                                        np.zeros((1, 4)), np.zeros(3)))
            done.set()
            writer.close()

        server = await asyncio.start_server(viewer, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        async with NetworkProxy("127.0.0.1", port, parse_network_spec(spec)) as proxy:
            _, writer = await asyncio.open_connection("127.0.0.1", proxy.port)
            start = time.perf_counter()
            for seq in range(180):  # two seconds of frames, on an absolute schedule
                await asyncio.sleep(max(start + seq / 90.0 - time.perf_counter(), 0.0))
                writer.write(seq.to_bytes(8, "big")
                             + np.array([time.perf_counter()], ">f8").tobytes())
            await writer.drain()
            writer.close()
            await asyncio.wait_for(done.wait(), WAIT)
        server.close()
        return buffer.delay

    async def both() -> tuple[float, float]:
        calm, jittery = await asyncio.gather(through("40ms,seed=1"),
                                             through("40ms+-20ms,seed=1"))
        return calm, jittery

    calm, jittery = asyncio.run(both())
    print(f"playout delay: calm {calm * 1e3:.1f} ms, jittery {jittery * 1e3:.1f} ms")
    # calm: about one capture interval (11 ms); jittery: +-20 ms spreads arrivals over
    # some 40 ms, which the buffer covers (generous margins: a loaded machine adds jitter
    # to both)
    assert jittery >= 0.030, (calm, jittery)
    assert jittery > calm + 0.015, (calm, jittery)
