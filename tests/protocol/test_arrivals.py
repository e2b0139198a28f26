"""protocol/arrivals.py on real sockets: a connection's fast path takes the binary
messages it accepts as they are read (a read that is one whole frame skips websockets'
parser), is asked once about each message, and the reading task gets the rest in
order."""

from __future__ import annotations

import asyncio
import time

from websockets.asyncio.client import connect
from websockets.asyncio.server import ServerConnection, serve

from posecast.protocol.arrivals import ArrivalStamps, Data, arrival_time

TIMEOUT = 10.0


class _Stamped(ArrivalStamps, ServerConnection):
    clock = staticmethod(time.perf_counter)


def test_the_fast_path_is_asked_once_a_message_and_the_task_gets_the_rest() -> None:
    sent: list[bytes | str] = [b"F1", b"X2", "text 3", b"F4" * 100, b"X5" * 100, b"F6"]

    async def main() -> tuple[list[tuple[str, bytes | str]], list[bytes]]:
        seen: list[tuple[str, bytes | str]] = []
        asked: list[bytes] = []

        def fast(data: Data, t: float) -> bool:
            asked.append(bytes(data))
            if bytes(data).startswith(b"F"):
                seen.append(("fast", bytes(data)))
                return True
            return False

        async def handler(ws: ServerConnection) -> None:
            ws.fast_path = fast  # type: ignore[attr-defined]
            await ws.send("ready")
            async for message in ws:
                arrival_time(ws, time.perf_counter)  # its stamp, as every reader takes it
                seen.append(("task", message))

        async with serve(handler, "127.0.0.1", 0, compression=None,
                         create_connection=_Stamped) as server:
            port = next(iter(server.sockets)).getsockname()[1]
            async with connect(f"ws://127.0.0.1:{port}", compression=None) as ws:
                assert await ws.recv() == "ready"
                for i, message in enumerate(sent):  # each its own write and read, mostly
                    await ws.send(message)
                    await asyncio.sleep(0.005)
                    if i == 2:
                        await ws.ping()  # a control frame between: websockets' own
                        await asyncio.sleep(0.005)
                async with asyncio.timeout(TIMEOUT):
                    while len(seen) < len(sent):
                        await asyncio.sleep(0.01)
        return seen, asked

    seen, asked = asyncio.run(main())
    assert [m for _, m in seen] == sent  # every message once, in order
    assert [how for how, _ in seen] == ["fast", "task", "task", "fast", "task", "fast"]
    assert asked == [m for m in sent if isinstance(m, bytes)]  # asked once each
