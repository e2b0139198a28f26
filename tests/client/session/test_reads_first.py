"""Reads before decodes (``client.session.reads_first``), on a real event loop: the
messages a process's connections read are decoded once a pass of the loop read nothing
more, in the order their connections first read, and a stream of reads that never
pauses does not hold the decoding back for longer than SETTLE_MAX_S."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

from posecast.client.session.reads_first import SETTLE_MAX_S, ReadsFirst


async def _passes(n: int) -> None:
    for _ in range(n):
        await asyncio.sleep(0)  # one pass of the loop each


def test_a_lone_read_is_decoded_two_passes_later() -> None:
    async def main() -> list[int]:
        reads = ReadsFirst(asyncio.get_running_loop())
        decoded: list[int] = []
        reads.read(lambda: decoded.append(1))
        await _passes(1)
        seen = len(decoded)  # a pass has polled since the read: not yet
        await _passes(1)
        return [seen, len(decoded)]

    assert asyncio.run(main()) == [0, 1]


def test_reads_on_the_next_passes_are_taken_before_any_decode() -> None:
    """Three connections read on three passes in a row (a server writing to them one
    after the other): no decode comes between the reads, then all come in order."""

    async def main() -> list[str]:
        loop = asyncio.get_running_loop()
        reads = ReadsFirst(loop)
        events: list[str] = []

        def decoder(name: str) -> Callable[[], None]:
            return lambda: events.append(f"decode {name}")

        def read(name: str, then: list[str]) -> None:
            events.append(f"read {name}")
            reads.read(decoder(name))
            if then:  # the next connection's bytes come on the next pass
                loop.call_soon(read, then[0], then[1:])

        read("a", ["b", "c"])
        reads.read(None)  # a second message of a: its decoder is already waiting
        await _passes(8)
        return events

    assert asyncio.run(main()) == ["read a", "read b", "read c",
                                   "decode a", "decode b", "decode c"]


def test_reads_that_never_pause_do_not_starve_the_decode() -> None:
    async def main() -> tuple[int, int]:
        loop = asyncio.get_running_loop()
        reads = ReadsFirst(loop)
        decoded_at: list[int] = []
        count = 0
        t0 = time.perf_counter()
        stream_s = 40 * SETTLE_MAX_S

        def read() -> None:  # a read on every pass for stream_s, and 20 passes at least
            nonlocal count
            count += 1
            reads.read(None if count > 1 else lambda: decoded_at.append(count))
            if time.perf_counter() - t0 < stream_s or count < 20:
                loop.call_soon(read)

        read()
        while time.perf_counter() - t0 < stream_s or count < 20:
            await asyncio.sleep(0)
        await _passes(4)
        return decoded_at[0] if decoded_at else -1, count

    decoded_at, reads_in_all = asyncio.run(main())
    # decoded while the stream went on: after more reads than the first, before its end
    assert 1 < decoded_at < reads_in_all


def test_a_decoder_that_raises_leaves_the_others_theirs() -> None:
    async def main() -> tuple[list[str], list[object]]:
        loop = asyncio.get_running_loop()
        reported: list[object] = []
        loop.set_exception_handler(lambda _, context: reported.append(context["exception"]))
        reads = ReadsFirst(loop)
        decoded: list[str] = []

        def broken() -> None:
            raise RuntimeError("a bug")

        reads.read(broken)
        reads.read(lambda: decoded.append("b"))
        await _passes(4)
        reads.read(lambda: decoded.append("c"))  # and the next reads are decoded too
        await _passes(4)
        return decoded, reported

    decoded, reported = asyncio.run(main())
    assert decoded == ["b", "c"]
    assert len(reported) == 1 and isinstance(reported[0], RuntimeError)
