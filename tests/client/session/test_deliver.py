"""A spectator's messages handed over as the loop reads them (``Session.deliver``),
over a real server on 127.0.0.1: every batch arrives, in order, with the same figures
as through ``receive``, and a handler's bug ends the spectator's run with that error."""

from __future__ import annotations

import asyncio

import pytest
from conftest import serving

from posecast.client.builtin import builtin_motion_path
from posecast.client.session.connection import Session as ClientSession
from posecast.client.session.player import Player
from posecast.client.session.spectator import Spectator
from posecast.client.sources.bvh_source import BvhSource
from posecast.protocol import AvatarBatch, AvatarRoster, ClockEstimator
from posecast.server.app import Session

TIMEOUT = 60.0


class Counting(Spectator):
    """Keeps each batch's seqs, and whether ``receive`` or ``deliver`` handed it over;
    raises on the batch ``fail_at`` (1-based) if set."""

    def __init__(self, url: str, fail_at: int | None = None) -> None:
        super().__init__(url, "room", "watcher")
        self.seqs: list[int] = []
        self.fail_at = fail_at
        self.in_room = asyncio.Event()

    def on_roster(self, roster: AvatarRoster) -> None:
        super().on_roster(roster)
        self.in_room.set()

    def on_batch(self, batch: AvatarBatch, t_local: float, clock: ClockEstimator) -> None:
        super().on_batch(batch, t_local, clock)
        self.seqs.extend(batch.seqs.tolist())
        if self.fail_at is not None and self.stats.batches_received == self.fail_at:
            raise RuntimeError("a bug in on_batch")


def _play(url: str) -> Player:
    return Player(url, "room", "p", BvhSource(builtin_motion_path(), loop=True,
                                              rate_hz=90.0))


def test_a_spectator_gets_every_batch_in_order_as_the_loop_reads_it() -> None:
    async def main() -> tuple[Player, Counting, ClientSession]:
        async with serving(Session()) as url:
            spectator = Counting(url)
            watching = asyncio.create_task(spectator.run())
            async with asyncio.timeout(TIMEOUT):
                await spectator.in_room.wait()
            assert spectator.session is not None
            assert spectator.session.ws.fast_path is not None  # type: ignore[attr-defined]
            player = _play(url)
            await player.run(seconds=1.0)
            async with asyncio.timeout(TIMEOUT):
                while len(spectator.seqs) < player.stats.frames_sent:
                    await asyncio.sleep(0.02)
            session = spectator.session
            assert session is not None
            watching.cancel()
            await asyncio.gather(watching, return_exceptions=True)
            return player, spectator, session

    player, spectator, session = asyncio.run(main())
    assert player.stats.frames_sent > 60
    assert spectator.seqs == list(range(player.stats.frames_sent))  # all, in order
    assert spectator.stats.frames_received == player.stats.frames_sent
    assert not spectator.stats.errors
    assert session.bytes_received > 60 * 100  # counted on the way they came
    lat = spectator.stats.latency.summary()
    assert {"capture_to_server", "network_to_spectator", "capture_to_decoded"} <= set(lat)
    assert 0.0 < lat["network_to_spectator"]["p50"] < 1000.0


def test_a_handlers_bug_ends_the_run_with_its_error() -> None:
    async def main() -> Counting:
        async with serving(Session()) as url:
            spectator = Counting(url, fail_at=5)
            watching = asyncio.create_task(spectator.run())
            async with asyncio.timeout(TIMEOUT):
                await spectator.in_room.wait()
            player = asyncio.create_task(_play(url).run(seconds=3.0))
            with pytest.raises(RuntimeError, match="a bug in on_batch"):
                async with asyncio.timeout(TIMEOUT):
                    await watching
            await player
            assert spectator.session is not None
            assert spectator.session.ws.fast_path is None  # type: ignore[attr-defined]
            return spectator

    spectator = asyncio.run(main())
    assert spectator.stats.batches_received == 5  # nothing handed over after the bug
