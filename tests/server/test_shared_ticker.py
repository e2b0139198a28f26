"""Players sharing one schedule (the demo's 16 in one process) over a real server on
127.0.0.1: each player reads its source and writes its frame in its turn, as on a
machine of its own, so that no frame waits for the other players' reads."""

from __future__ import annotations

import asyncio

from conftest import serving

from posecast.client.builtin import builtin_motion_path
from posecast.client.session.player import Player, Ticker
from posecast.client.sources.base import DeviceSample
from posecast.client.sources.bvh_source import BvhSource
from posecast.server.app import Session

PLAYERS = 3


class Watched:
    """A source that notes, at each read, how many frames every player has sent."""

    def __init__(self, i: int, players: list[Player], seen: list[tuple[int, list[int]]]
                 ) -> None:
        self.source = BvhSource(builtin_motion_path(), loop=True, rate_hz=90.0,
                                offset=(1.5 * i, 0.0))
        self.rate_hz = self.source.rate_hz
        self.i, self.players, self.seen = i, players, seen

    def calibration(self) -> DeviceSample:
        return self.source.calibration()

    def read(self) -> DeviceSample | None:
        self.seen.append((self.i, [p.stats.frames_sent for p in self.players]))
        return self.source.read()

    def close(self) -> None:
        self.source.close()


def test_each_player_on_a_shared_ticker_sends_before_the_next_one_reads() -> None:
    seen: list[tuple[int, list[int]]] = []
    players: list[Player] = []
    sources = [Watched(i, players, seen) for i in range(PLAYERS)]

    async def main() -> None:
        async with serving(Session()) as url:
            ticker = Ticker(90.0)
            players.extend(Player(url, "tick", f"p{i}", s, ticker=ticker)
                           for i, s in enumerate(sources))
            await asyncio.gather(*(p.run(seconds=1.0) for p in players))

    asyncio.run(main())
    for s in sources:
        s.close()
    assert all(p.stats.frames_sent > 30 and p.stats.frames_dropped == 0 for p in players)
    # the slots where every player streamed: player i's read comes after the frames of
    # the players before it in this slot were sent, and before its own
    slots = [seen[k:k + PLAYERS] for k in range(0, len(seen) - PLAYERS + 1)
             if [i for i, _ in seen[k:k + PLAYERS]] == list(range(PLAYERS))]
    assert len(slots) > 30, len(seen)
    for slot in slots:
        first = slot[0][1]
        for i, sent in slot:
            expected = [first[j] + (1 if j < i else 0) for j in range(PLAYERS)]
            assert sent == expected, slot
