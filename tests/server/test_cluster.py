"""Server processes sharing rooms through Redis (issue 19): a real redis-server on
127.0.0.1, real servers and real clients. Players on one process and spectators on
another see the same frames; a player sent to the wrong process is redirected to the
owner; the owner killed, its players come back on another process, still calibrated."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import shutil
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator

import msgpack
import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families
from pydantic import ValidationError

from posecast.client import cli
from posecast.client.bench.fanout import BUDGET_MS, MAX_LOST, Step, _Search, held_step
from posecast.client.bench.redis_process import RedisMissingError, RedisProcess, free_port
from posecast.client.builtin import builtin_motion_path
from posecast.client.cli import main
from posecast.client.session.connection import Reconnect
from posecast.client.session.player import Player
from posecast.client.session.spectator import Spectator
from posecast.client.sources import open_source
from posecast.protocol import AvatarBatch, ClockEstimator, Redirect, decode, encode
from posecast.server.app import Session
from posecast.server.cluster import Cluster, owner_key
from posecast.server.relay import (
    BATCH,
    AvatarRecord,
    open_envelope,
    relay_envelope,
    relayed_batch,
    wall_minus_clock,
)
from posecast.server.serving import run_server

TIMEOUT = 60.0
QUICK = {"first_s": 0.05, "max_s": 0.2}


@pytest.fixture
def redis_url() -> Iterator[str]:
    try:
        with RedisProcess() as server:
            yield server.url
    except RedisMissingError as err:
        pytest.skip(str(err))


class Process:
    """A server with ``--redis`` in this event loop, on a port of its own."""

    def __init__(self, redis_url: str, grace: float = 30.0) -> None:
        self.port = free_port()
        self.url = f"ws://127.0.0.1:{self.port}"
        self.cluster = Cluster(redis_url, self.url)
        self.session = Session(reconnect_grace=grace, cluster=self.cluster)
        self._stop = asyncio.Event()
        self._task: asyncio.Task[Session] | None = None

    async def __aenter__(self) -> Process:
        ready: asyncio.Future[int] = asyncio.get_running_loop().create_future()
        self._task = asyncio.create_task(run_server("127.0.0.1", self.port, self.session,
                                                    self._stop, ready.set_result))
        await asyncio.wait_for(ready, TIMEOUT)
        return self

    async def __aexit__(self, *exc: object) -> None:
        self._stop.set()
        assert self._task is not None
        await asyncio.wait_for(self._task, TIMEOUT)


class Keeping(Spectator):
    """A spectator that keeps every (avatar, seq) -> rotations it receives."""

    def __init__(self, url: str, room: str, name: str) -> None:
        super().__init__(url, room, name)
        self.frames: dict[tuple[int, int], np.ndarray] = {}
        self.arrived: dict[int, float] = {}  # each avatar's last frame, time.monotonic()

    def on_batch(self, batch: AvatarBatch, t_local: float, clock: ClockEstimator) -> None:
        super().on_batch(batch, t_local, clock)
        for frame in batch.frames:
            self.frames[(frame.avatar_id, frame.seq)] = frame.rotations.copy()
            self.arrived[frame.avatar_id] = time.monotonic()


def _get(url: str) -> str:
    with urllib.request.urlopen(url, timeout=TIMEOUT) as reply:
        return str(reply.read().decode())


async def until(condition: object, what: str) -> None:
    t_end = time.monotonic() + TIMEOUT
    while not condition():  # type: ignore[operator]
        assert time.monotonic() < t_end, f"timed out waiting for {what}"
        await asyncio.sleep(0.02)


@contextlib.asynccontextmanager
async def running(*clients: Player | Spectator):  # type: ignore[no-untyped-def]
    stop = asyncio.Event()
    tasks = [asyncio.create_task(c.run(stop=stop)) for c in clients]
    try:
        yield tasks
    finally:
        stop.set()
        await asyncio.wait_for(asyncio.gather(*tasks, return_exceptions=True), TIMEOUT)


def test_a_spectator_on_another_process_receives_every_frame_the_owner_solved(
        redis_url: str) -> None:
    async def main() -> None:
        async with Process(redis_url) as a, Process(redis_url) as b:
            here = Keeping(a.url, "show", "on a")
            far = Keeping(b.url, "show", "on b")
            sources = [open_source(f"bvh:{builtin_motion_path()}", loop=True)
                       for _ in range(2)]
            players = [Player(a.url, "show", f"p{i}", s) for i, s in enumerate(sources)]
            async with running(here, far):
                await until(lambda: "show" in b.session.rooms, "the far spectator in")
                await until(lambda: "show" in a.session.rooms, "the near spectator in")
                async with running(*players):
                    await until(lambda: len(far.frames) > 200, "frames through Redis")
                    ids = {p.stats.avatar_id for p in players}
                    assert set(far.roster) == set(here.roster) == ids
                await until(lambda: not far.roster, "the players' leaving, through Redis")
                await until(lambda: b.session.metrics.frames_relayed
                            == a.session.metrics.frames_solved, "the last relayed")
                await asyncio.sleep(0.2)
            for s in sources:
                s.close()
            solved = a.session.metrics.frames_solved
            assert b.session.metrics.frames_relayed == solved  # every one, through Redis
            assert b.session.metrics.frames_solved == 0  # nothing solved twice
            # what the far spectator missed is counted (latest wins), never lost silently
            assert len(far.frames) + b.session.metrics.frames_dropped == solved
            assert len(far.frames) >= 0.95 * solved
            shared = set(far.frames) & set(here.frames)
            assert len(shared) >= 0.9 * solved
            for key in shared:  # the same bytes: the same rotations exactly
                np.testing.assert_array_equal(far.frames[key], here.frames[key])
            relay = b.session.metrics.relay_latency
            assert relay.count("relay") > 0
            text = await asyncio.to_thread(_get, b.url.replace("ws://", "http://")
                                           + "/metrics")
            scraped = {(m.name, tuple(sorted(x.labels.items()))): x.value
                       for m in text_string_to_metric_families(text) for x in m.samples}
            assert scraped[("posecast_redis_up", ())] == 1
            assert scraped[("posecast_cluster_events", (("event", "relayed"),))] \
                == b.cluster.stats.relayed > 0

    asyncio.run(main())


def test_a_player_joining_another_process_is_sent_to_the_owner(redis_url: str) -> None:
    async def main() -> None:
        async with Process(redis_url) as a, Process(redis_url) as b:
            first_source = open_source(f"bvh:{builtin_motion_path()}", loop=True)
            second_source = open_source(f"bvh:{builtin_motion_path()}", loop=True)
            first = Player(a.url, "match", "first", first_source)
            second = Player(b.url, "match", "second", second_source)  # redirected to A
            async with running(first):
                await until(lambda: a.session.metrics.frames_solved > 10, "A owns the room")
                async with running(second):
                    await until(lambda: second.stats.avatar_id is not None
                                and second.stats.frames_sent > 20, "the second streaming")
                    room = a.session.rooms["match"]
                    assert {first.stats.avatar_id, second.stats.avatar_id} <= set(room.avatars)
                    assert "match" not in b.session.rooms  # no spectator there
                    assert b.cluster.stats.redirects == 1
            first_source.close()
            second_source.close()

    asyncio.run(main())


# ---------------------------------------------------------------------- failover
def test_the_owner_killed_its_players_stream_through_another_process_calibrated(
        redis_url: str) -> None:
    """4 players on process A (a real `posecast serve --redis`), a spectator on B; A gets
    SIGKILL. The players (given both URLs, with the default backoff) come back through
    B with their avatars, calibrated, within 3 s; the spectator never leaves B."""
    port = free_port()
    a_url = f"ws://127.0.0.1:{port}"
    said: list[str] = []

    async def main() -> None:
        serve = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "posecast.client.cli", "serve", "--port", str(port),
            "--redis", redis_url, "--log-level", "warning",
            stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE)
        try:
            await until_listening(port, serve)
            async with Process(redis_url) as b:
                viewer = Keeping(b.url, "stage", "on b")
                sources = [open_source(f"bvh:{builtin_motion_path()}", loop=True)
                           for _ in range(4)]
                urls = f"{a_url},{b.url}"
                players = [Player(urls, "stage", f"p{i}", s, reconnect=Reconnect(
                    say=said.append)) for i, s in enumerate(sources)]
                async with running(viewer):
                    await until(lambda: "stage" in b.session.rooms, "the spectator in")
                    async with running(*players):
                        await until(lambda: all(p.stats.avatar_id for p in players),
                                    "the players in")
                        ids = {p.stats.avatar_id for p in players}
                        await until(lambda: set(viewer.roster) == ids
                                    and len(viewer.frames) > 100, "frames from A")
                        assert b.session.metrics.frames_solved == 0
                        serve.kill()  # SIGKILL: no goodbye, its keys stay until they expire
                        await serve.wait()
                        t_killed = time.monotonic()
                        solved_by_b: dict[int, float] = {}

                        def back() -> bool:
                            """Each avatar's first frame solved by B: A is dead, so
                            what the viewer gets once B owns the room is B's."""
                            room = b.session.rooms.get("stage")
                            if room is None or room.relayed:
                                return False
                            if not solved_by_b:
                                solved_by_b[0] = time.monotonic()  # B owns it from here
                            for avatar_id, t in viewer.arrived.items():
                                if avatar_id not in solved_by_b and t > solved_by_b[0]:
                                    solved_by_b[avatar_id] = t - t_killed
                            return set(solved_by_b) == ids | {0}
                        await until(back, "every player streaming through B")
                        back_in = max(t for a, t in solved_by_b.items() if a)
                        print(f"all 4 players streaming through B {back_in:.2f} s after "
                              f"the kill")
                        assert back_in <= 3.0
                        await asyncio.sleep(0.3)
                        assert set(viewer.roster) == ids  # the same avatars
                        assert {p.stats.avatar_id for p in players} == ids
                        assert all(p.stats.calibrations_sent == 1 for p in players)
                        assert all(p.stats.reconnects == 1 for p in players)
                        assert viewer.stats.reconnects == 0  # it stayed on B throughout
                        assert b.cluster.stats.takeovers == 1
                for s in sources:
                    s.close()
        finally:
            if serve.returncode is None:
                serve.kill()
                await serve.wait()

    asyncio.run(main())
    assert sum("avatar resumed, still calibrated" in line for line in said) == 4, said


async def until_listening(port: int, proc: asyncio.subprocess.Process) -> None:
    t_end = time.monotonic() + TIMEOUT
    while True:
        try:
            _, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.close()
            return
        except OSError:
            if proc.returncode is not None:
                err = await proc.stderr.read() if proc.stderr else b""
                raise AssertionError(f"serve exited: {err.decode()[-500:]}") from None
            assert time.monotonic() < t_end, "serve did not listen"
            await asyncio.sleep(0.05)


# ---------------------------------------------------------------------- Redis lost
def test_redis_lost_while_running_keeps_each_room_local_and_rejoins_when_back() -> None:
    """Redis killed under a room owned by A with a spectator on A and one on B: A's
    player and spectator carry on (logged once); a new room still opens on B. Redis back
    (empty, as a restarted in-memory one is): A claims its room again and writes its
    avatar's calibration again, and B's spectator gets the frames again."""
    try:
        redis_server = RedisProcess().start()
    except RedisMissingError as err:
        pytest.skip(str(err))
    port = redis_server.port
    back = RedisProcess(port)

    async def main() -> None:
        async with Process(redis_server.url) as a, Process(redis_server.url) as b:
            near = Keeping(a.url, "live", "on a")
            far = Keeping(b.url, "live", "on b")
            source = open_source(f"bvh:{builtin_motion_path()}", loop=True)
            other_source = open_source(f"bvh:{builtin_motion_path()}", loop=True)
            player = Player(a.url, "live", "pat", source)
            async with running(near, far):
                await until(lambda: "live" in b.session.rooms and "live" in a.session.rooms,
                            "the spectators in")
                async with running(player):
                    await until(lambda: len(far.frames) > 30, "frames through Redis")
                    redis_server.stop()
                    await until(lambda: not a.cluster.up, "A to notice")
                    solved = a.session.metrics.frames_solved
                    seen = len(near.frames)
                    # the room goes on, solved by A: both counts move on (a frame in
                    # flight when they were read may count in one and not the other)
                    await until(lambda: len(near.frames) > seen + 90, "A's room going on")
                    await until(lambda: a.session.metrics.frames_solved > solved + 90,
                                "A solving on")
                    # a room opened while Redis is gone is served where it is joined
                    lone = Player(b.url, "alone", "lee", other_source)
                    async with running(lone):
                        await until(lambda: b.session.metrics.frames_solved > 20,
                                    "a new room on B")
                    back.start()  # Redis back, empty
                    await until(lambda: a.cluster.up and b.cluster.up, "both to rejoin")
                    await until(lambda: far.arrived.get(player.stats.avatar_id or 0, 0)
                                > time.monotonic() - 0.1, "frames through Redis again")
                    check = Cluster(redis_server.url, "ws://127.0.0.1:1")
                    check.up = True  # a reader only: not started, not one of the service
                    owner = await check.redis.get(owner_key("live"))
                    assert owner is not None and a.cluster.process_id in owner.decode()
                    records = await check.records("live")
                    assert [r.avatar_id for r in records] == [player.stats.avatar_id]
                    assert records[0].poses is not None  # its T-pose: calibrated again
                    await check.redis.aclose()
            assert player.stats.reconnects == 0 and near.stats.reconnects == 0
            assert a.cluster.stats.lost == 1
            source.close()
            other_source.close()

    try:
        asyncio.run(main())
    finally:
        back.stop()
        redis_server.stop()


# ---------------------------------------------------------------------- edges
def test_serve_with_redis_unreachable_says_so_in_one_line() -> None:
    url = f"redis://127.0.0.1:{free_port()}"  # nothing listens there
    done = subprocess.run([sys.executable, "-m", "posecast.client.cli", "serve", "--port",
                           "0", "--redis", url], capture_output=True, text=True,
                          timeout=TIMEOUT)
    assert done.returncode == 1
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"posecast serve: cannot use Redis at {url}: ")
    assert "Connection refused" in lines[0] and "redis-server" in lines[0]


def test_an_envelope_from_another_machine_is_moved_onto_this_clock() -> None:
    """Another machine's clock is another origin: the receiver moves every time of a
    batch by the difference of the two wall-minus-clock offsets, and keeps the poses."""
    rotations = np.tile([0.0, 0.0, 0.0, 1.0], (2, 3, 1))
    rotations[1, 2] = [0.0, np.sin(0.3), 0.0, np.cos(0.3)]
    batch = AvatarBatch.from_arrays([7, 9], [1, 2], np.zeros((2, 3)), rotations,
                                    [10.0, 10.5], [10.1, 10.6], 10.7, 10.8)
    payload = encode(batch)
    far = msgpack.packb((BATCH, "other", 11.0, wall_minus_clock() - 1000.0, payload),
                        use_bin_type=True)
    envelope = open_envelope(far)
    assert envelope.shift == pytest.approx(-1000.0, abs=1e-3)
    data, moved = relayed_batch(envelope, {})
    np.testing.assert_allclose(moved.t_capture, batch.t_capture - 1000.0, atol=1e-3)
    assert moved.t_sent == pytest.approx(10.8 - 1000.0, abs=1e-3)
    sent = decode(payload)  # as the owner's spectators get it (quantized)
    assert isinstance(sent, AvatarBatch)
    np.testing.assert_allclose(moved.rotations, sent.rotations, atol=1e-6)
    assert decode(data) == moved
    near = relay_envelope(BATCH, "same", payload)  # this machine: the bytes go on as they are
    assert relayed_batch(open_envelope(near), {})[0] is not None
    assert open_envelope(near).shift == 0.0 \
        and relayed_batch(open_envelope(near), {})[0] == payload
    for junk in (b"", b"\x93\x01\x02\x03", msgpack.packb(("x", "s", 1.0, 0.0, b""))):
        with pytest.raises(ValueError, match="not a relay envelope"):
            open_envelope(junk)


def test_an_avatar_record_comes_back_as_it_was_kept() -> None:
    poses = np.arange(21, dtype=np.float64).reshape(3, 7)
    record = AvatarRecord(12, "ana", "secret", None, ("head", "left_hand", "right_hand"),
                          poses)
    back = AvatarRecord.unpack(record.pack())
    assert (back.avatar_id, back.display_name, back.resume, back.roles) == (
        12, "ana", "secret", ("head", "left_hand", "right_hand"))
    assert back.poses is not None
    np.testing.assert_array_equal(back.poses, poses)
    for junk in (b"\xc1", msgpack.packb({"id": 1}), "text"):
        with pytest.raises(ValueError, match="not an avatar record"):
            AvatarRecord.unpack(junk)


def test_a_redirect_names_a_websocket_url() -> None:
    assert Redirect(url="wss://host/s2").url == "wss://host/s2"
    for bad in ("http://host/", "javascript:alert(1)", ""):
        with pytest.raises(ValidationError):
            Redirect(url=bad)


def test_bench_fanout_measures_each_process_count(
        capsys: pytest.CaptureFixture[str]) -> None:
    """The bench's machinery at a toy size: both process counts reach the cap with every
    probe's latency measured and the players' frames reaching every spectator, a line
    per step as it goes. A step that fails once is tried again (the bench's own rule
    against a loaded machine's hiccup), so a count may appear twice, failed then held.
    One count a run (the start is the cap): the search's steps are _Search's test's."""
    if shutil.which("redis-server") is None:
        pytest.skip("no redis-server here (apt-get install redis-server)")
    assert main(["bench", "fanout", "--processes", "1,2", "--start", "9", "--max", "9",
                 "--seconds", "3", "--budget-ms", "1000", "--repeat", "2", "--json"]) == 0
    out = capsys.readouterr()
    doc = json.loads(out.out)
    assert doc["budget_ms"] == 1000 and doc["max_lost"] == MAX_LOST and doc["repeat"] == 2
    assert [r["processes"] for r in doc["results"]] == [1, 2]
    steps_seen = 0
    for r in doc["results"]:
        assert r["spectators"] == 9 and r["runs"] == [9, 9] and r["ratios"] == [1.0, 1.0]
        assert len(r["steps"]) == 2  # a list of steps per run
        for run in r["steps"]:
            held = [s for s in run if s["held"]]
            assert [s["spectators"] for s in held] == [9]
            # a failed step is followed by the same count again, which then held
            for before, after in itertools.pairwise(run):
                if not before["held"]:
                    assert after["spectators"] == before["spectators"] and after["held"]
            steps_seen += len(run)
            for step in run:
                assert len(step["capture_to_spectator_p99_ms"]) == r["processes"]
                assert all(p > 0 for p in step["capture_to_spectator_p99_ms"])
            for step in held:
                assert all(p < 1000 for p in step["capture_to_spectator_p99_ms"])
                # every spectator got the players' frames (within a batch at each end
                # of the window: a burst may be open when the counters are read)
                assert all(0 <= x <= MAX_LOST for x in step["lost"])
        assert r["capture_to_spectator_p99_ms"] == r["steps"][0][-1][
            "capture_to_spectator_p99_ms"]
    assert doc["results"][1]["ratio"] == 1.0
    assert out.err.count("spectators: p99") == steps_seen >= 4


def test_bench_fanout_budget_is_the_cli_default() -> None:
    assert cli._FANOUT_BUDGET_MS == BUDGET_MS


def test_bench_fanout_search_needs_a_count_to_fail_twice_and_stops_within_3_percent(
        ) -> None:
    """The search's counts for a process that holds up to 700 spectators, with one
    stray failure at 300: it tries 300 again, grows x1.5 until a count fails twice, then
    halves the gap until it is within 1/32 of the first count that failed."""
    search = _Search(processes=1, n=200, max_spectators=20000)
    stray = {300}
    tried = []
    while not search.done:
        n = search.n
        tried.append(n)
        held = n <= 700 and not (n in stray and tried.count(n) == 1)
        search.record(Step(1, n, [1.0], [0.0 if held else 0.05], held))
    assert tried[:7] == [200, 300, 300, 450, 675, 1013, 1013]
    assert search.low <= 700 < search.high
    assert search.high - search.low <= search.high // 32
    assert held_step(search.steps) is not None
    assert held_step(search.steps).spectators == search.low  # type: ignore[union-attr]


def test_bench_fanout_gives_a_lone_server_a_core_of_its_own() -> None:
    """Where the machine has cores no server takes, the spectators, players and Redis
    go there; where it has none, each server's spectators share its core (every server
    then pays for its own alike) and Redis the last server's; a one-core machine pins
    nothing."""
    from posecast.client.bench.fanout import Placement, placement

    assert placement(1, (0, 1)) == Placement([1], "core:1", "core:1")
    assert placement(2, (0, 1, 2, 3)) == Placement([2, 3], "core:2", "core:2")
    assert placement(3, (0, 1, 2, 3)) == Placement([3, 3, 3], "core:3", "core:3")
    assert placement(2, (0, 1)) == Placement([0, 1], "core:0", "core:1")
    assert placement(1, (5,)) == Placement([None], "core:0", "core:0")
