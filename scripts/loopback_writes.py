#!/usr/bin/env python3
"""What one write to a loopback TCP socket costs this machine: the floor under
`posecast bench fanout`, whose server writes every batch to every spectator's socket.

    python scripts/loopback_writes.py [--sockets 600] [--bytes 500] [--seconds 10]

A writer pinned to the first core sends ``--bytes`` to each of ``--sockets`` connected
sockets, 90 times a second (a room's batches), with nothing else to do: no framing, no
checks, no event loop. Readers in another process, on another core where there is one,
read them dry every 20 ms with bench fanout's own load (``ByteCounter``). It prints the
writer's CPU time per write (user and system: on loopback the kernel runs the receiving
side of each send on the sender's core too) and the most spectators one core could then
feed at 90 Hz with writes alone.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import resource
import socket
import time
from multiprocessing.synchronize import Event

from posecast.client.bench.demo import HEADSET_HZ as RATE_HZ  # a room's batches a second
from posecast.client.bench.demo import demo_cores
from posecast.client.bench.fanout import SWEEP_S, ByteCounter


def _readers(port: int, count: int, core: int | None, stop: Event) -> None:
    """``count`` sockets read dry every SWEEP_S, as bench fanout's load reads them."""
    if core is not None:
        os.sched_setaffinity(0, {core})
    sockets = [socket.create_connection(("127.0.0.1", port)) for _ in range(count)]
    counter = ByteCounter()
    for s in sockets:
        s.setblocking(False)
        counter.add(s.fileno())
    while not stop.wait(SWEEP_S):
        counter.sweep()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sockets", type=int, default=600)
    parser.add_argument("--bytes", type=int, default=500, help="each write's size")
    parser.add_argument("--seconds", type=float, default=10.0)
    args = parser.parse_args()
    if not 1 <= args.sockets <= 20_000 or not 1 <= args.bytes <= 1 << 20 \
            or not 0 < args.seconds <= 600:
        parser.error("--sockets 1-20000, --bytes 1-1048576 and --seconds (0, 600] please")
    _soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and 2 * args.sockets + 64 > hard:
        parser.error(f"--sockets {args.sockets} needs {2 * args.sockets + 64} open files; "
                     f"this shell allows {hard} (ulimit -n)")
    resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
    cores = demo_cores()
    if cores:
        os.sched_setaffinity(0, {cores[0]})
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(min(args.sockets, 4096))
    stop = mp.get_context("spawn").Event()
    readers = mp.get_context("spawn").Process(
        target=_readers, args=(listener.getsockname()[1], args.sockets,
                               cores[1] if len(cores) > 1 else None, stop), daemon=True)
    readers.start()
    connections = [listener.accept()[0] for _ in range(args.sockets)]
    for c in connections:
        c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # as asyncio's transports
        c.setblocking(False)
    fds = [c.fileno() for c in connections]
    data = b"x" * args.bytes
    rounds = max(1, round(args.seconds * RATE_HZ))
    print(f"{args.sockets} sockets, {args.bytes} B each, {rounds} rounds at "
          f"{RATE_HZ:g} Hz ...", flush=True)
    cpu0, start = time.process_time(), time.perf_counter()
    late = 0
    for r in range(rounds):
        for fd in fds:
            try:
                os.write(fd, data)
            except BlockingIOError:  # a full socket: the readers fell behind
                late += 1
        wait = start + (r + 1) / RATE_HZ - time.perf_counter()
        if wait > 0:
            time.sleep(wait)
    cpu = time.process_time() - cpu0
    stop.set()
    readers.join(10)
    per_write = cpu / (rounds * args.sockets)
    print(f"CPU per write: {1e6 * per_write:.2f} us; writes alone fill one core at "
          f"{1 / (RATE_HZ * per_write):,.0f} spectators of a {RATE_HZ:g} Hz room"
          + (f" ({late} writes refused: a socket was full)" if late else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
