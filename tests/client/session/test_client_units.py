"""client/ player, spectator, latency and connection pieces that need no server.

The latency recorder against numpy's percentiles, the player's absolute schedule, the
messages built from a DeviceSample (exact through the codec), the spectator's bookkeeping
of batches and rosters, the latency table, and connection errors as one line.
"""

from __future__ import annotations

import asyncio
import socket
import time

import numpy as np
import pytest
import uvloop

from posecast.client.builtin import builtin_motion_path
from posecast.client.measure.latency import LatencyRecorder, format_latency_table
from posecast.client.session.connection import SessionError, open_session
from posecast.client.session.player import Ticker, calibrate_message, tracker_frame
from posecast.client.session.spectator import Spectator, frame_of
from posecast.client.sources.base import DeviceSample
from posecast.client.sources.bvh_source import BvhSource
from posecast.protocol import (
    PROTOCOL_VERSION,
    AvatarBatch,
    AvatarFrame,
    AvatarInfo,
    AvatarRoster,
    Calibrate,
    ClockEstimator,
    Hello,
    TrackerFrame,
    decode,
    encode,
    encode_tracker_frame,
)


# --------------------------------------------------------------------------- latency
def test_recorder_percentiles_equal_numpy() -> None:
    rng = np.random.default_rng(3)
    a = rng.lognormal(-7.0, 0.5, 5000)  # seconds, ~1 ms with a tail
    b = rng.uniform(0.0, 0.01, 777)
    rec = LatencyRecorder(capacity=8)  # tiny, so appends grow the buffer many times
    for x, y in zip(a, b, strict=False):
        rec.add({"server": x, "capture_to_spectator": y})
    rec.add_values("server", a[len(b):])
    summary = rec.summary()
    for stage, values in (("server", a), ("capture_to_spectator", b)):
        expect = np.percentile(values, [50, 95, 99]) * 1e3
        got = [summary[stage][k] for k in ("p50", "p95", "p99")]
        np.testing.assert_allclose(got, expect, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(rec.samples(stage), values)
    assert rec.counts() == {"server": 5000, "capture_to_spectator": 777}
    assert len(rec) == 5000


def test_recorders_merge_over_all_samples() -> None:
    rng = np.random.default_rng(4)
    parts = [rng.exponential(0.001, n) for n in (10, 2000, 333)]
    recs = []
    for p in parts:
        r = LatencyRecorder()
        r.add_values("solve", p)
        recs.append(r)
    merged = LatencyRecorder.merged(recs)
    every = np.concatenate(parts)
    assert merged.summary()["solve"]["p99"] == pytest.approx(
        float(np.percentile(every, 99)) * 1e3, abs=1e-12)
    assert merged.counts() == {"solve": every.size}
    assert recs[0].counts() == {"solve": 10}  # the parts are left as they were


def test_batch_times_give_the_stages_of_each_frame() -> None:
    """add_batch keeps raw times and computes stages when read: the same samples as
    adding each frame's latencies, and no receive-side stages for a batch received
    before the clock was synced."""
    rng = np.random.default_rng(5)
    rec = LatencyRecorder(capacity=4)  # tiny: the time columns grow too
    expected = LatencyRecorder()
    for k in range(300):
        n = int(rng.integers(1, 9))
        t_capture = 100.0 + k / 90 + rng.uniform(0.0, 0.001, n)
        t_server_receive = t_capture + rng.uniform(0.0002, 0.002, n)
        t_solved = t_server_receive + rng.uniform(0.0001, 0.001, n)
        t_sent = float(t_solved.max()) + 0.00005
        t_received = None if k % 7 == 3 else t_sent + 0.0004
        t_decoded = None if t_received is None or k % 5 == 1 else t_received + 0.0003
        rec.add_batch(t_capture, t_server_receive, t_solved, t_sent, t_received, t_decoded)
        for i in range(n):
            expected.add(AvatarFrame(avatar_id=i + 1, seq=k, root=[0.0, 1.0, 0.0],
                                     rotations=[[0.0, 0.0, 0.0, 1.0]],
                                     t_capture=t_capture[i],
                                     t_server_receive=t_server_receive[i],
                                     t_solved=t_solved[i], t_sent=t_sent
                                     ).latencies(t_received=t_received))
            if t_decoded is not None:
                expected.add_values("capture_to_decoded",
                                    np.array([t_decoded - t_capture[i]]))
        if k in (20, 150):  # reading in between, then adding more, loses nothing
            assert rec.counts()["server"] == expected.counts()["server"]
    assert rec.counts() == expected.counts()
    assert rec.counts()["capture_to_spectator"] < rec.counts()["server"]
    assert 0 < rec.counts()["capture_to_decoded"] < rec.counts()["capture_to_spectator"]
    for stage in expected.stages:
        np.testing.assert_allclose(np.sort(rec.samples(stage)),
                                   np.sort(expected.samples(stage)), rtol=0, atol=1e-12)


def test_empty_recorder() -> None:
    rec = LatencyRecorder()
    assert rec.summary() == {} and rec.counts() == {} and len(rec) == 0
    assert rec.samples("server").size == 0


def test_latency_table_aligned_in_pipeline_order() -> None:
    summary = {"capture_to_spectator": {"p50": 1.23456, "p95": 2.0, "p99": 12.5},
               "server": {"p50": 0.1, "p95": 0.25, "p99": float("nan")},
               "capture_to_server": {"p50": -0.004, "p95": 0.5, "p99": 0.75}}
    text = format_latency_table(summary, {"server": 28800, "capture_to_server": 28800,
                                          "capture_to_spectator": 460800})
    lines = text.splitlines()
    assert lines[0].split() == ["stage", "samples", "p50", "ms", "p95", "ms", "p99", "ms"]
    assert [ln.split()[0] for ln in lines[1:]] == ["capture_to_server", "server",
                                                   "capture_to_spectator"]
    assert lines[3].split()[1:] == ["460800", "1.235", "2.000", "12.500"]
    assert lines[2].split()[-1] == "-"  # NaN: no value, not "nan"
    assert lines[1].split()[2] == "-0.004"
    # right-aligned numbers: every column ends at the same place on every line
    ends = [_word_ends(ln) for ln in lines]
    header_ends = [e for e, w in zip(ends[0], lines[0].split(), strict=True) if w != "p50"
                   and w != "p95" and w != "p99"]
    assert all(e[1:] == header_ends[1:] for e in ends[1:])
    assert len({len(ln) for ln in lines}) == 1
    plain = format_latency_table(summary, decimals=2).splitlines()
    assert plain[0].split()[:2] == ["stage", "p50"] and plain[3].split()[1] == "1.23"


def _word_ends(line: str) -> list[int]:
    return [i + 1 for i, c in enumerate(line)
            if c != " " and (i + 1 == len(line) or line[i + 1] == " ")]


# --------------------------------------------------------------------------- ticker
def test_ticker_slots_are_absolute() -> None:
    t = Ticker(90.0, start=1000.0)
    # k / rate, not a running sum of periods: no drift after a day of slots
    assert t.slot_time(90 * 86400) == pytest.approx(1000.0 + 86400.0, abs=1e-9)
    assert t.next_slot(-1, 1000.0) == 0
    assert t.next_slot(0, 1000.0 + 0.2 / 90) == 1  # early: the next slot, waited for
    for k in range(1, 2000):  # exactly at a slot time: that slot, whatever the rounding
        assert t.next_slot(k - 1, t.slot_time(k)) == k
        assert t.next_slot(k - 2, t.slot_time(k) - 1e-9) == k - 1


def test_ticker_skips_late_slots_instead_of_bursting() -> None:
    t = Ticker(100.0, start=0.0)
    # served slot 2, woke at 5.5 periods: slot 5 now; 3 and 4 are skipped
    assert t.next_slot(2, 0.055) == 5
    assert t.next_slot(5, 0.0551) == 6  # then back on the grid


@pytest.mark.parametrize("loop", ["asyncio", "uvloop"])
def test_ticker_calls_on_the_schedule(loop: str) -> None:
    """Asserted against the ticker's own clock as it was read at each call, so that a
    loaded machine (late wake-ups, skipped slots) changes what is called, not whether
    the ticker did right."""
    async def main() -> tuple[Ticker, list[int], list[float], float]:
        ticker = Ticker(50.0)  # 20 ms slots
        slots: list[int] = []
        called: list[float] = []  # the ticker's clock at each call
        blocked_until = 0.0
        done = asyncio.get_running_loop().create_future()

        def on_slot(k: int) -> None:
            nonlocal blocked_until
            slots.append(k)
            called.append(ticker.clock())
            if len(slots) == 9:
                time.sleep(0.07)  # block the loop 3.5 periods: 3 more slots come due
                blocked_until = ticker.clock()
            if len(slots) == 10:
                done.set_result(None)

        ticker.subscribe(on_slot)  # slot 0, at once, starts the schedule
        await done
        ticker.unsubscribe(on_slot)
        return ticker, slots, called, blocked_until

    ticker, slots, called, blocked_until = (asyncio.run(main()) if loop == "asyncio"
                                            else uvloop.run(main()))
    assert slots[0] == 0
    # never early (uvloop rounds its timers to the millisecond; the ticker waits out
    # the rest); late only by the loop's own lateness: each slot is the next one, or,
    # when the loop woke late, the latest one due when the ticker re-armed (between the
    # end of the call before and this call), never a burst of the missed ones
    late = [t - ticker.slot_time(k) for k, t in zip(slots, called, strict=True)]
    assert min(late) >= 0.0, late
    armed_after = [*called[:8], blocked_until]
    for i in range(9):
        assert (ticker.next_slot(slots[i], armed_after[i]) <= slots[i + 1]
                <= ticker.next_slot(slots[i], called[i + 1])), (i, slots, called)
    assert slots[9] >= slots[8] + 3  # of the 3 slots due while blocked, the latest only
    # on time when the loop is: at least one wake-up of nine within a period (a ticker
    # that always slept a period too long would fail this whatever the load)
    assert min(late) < ticker.period, late


def test_shared_ticker_calls_every_player_on_one_slot() -> None:
    async def main() -> None:
        ticker = Ticker(50.0)
        calls: list[tuple[int, int]] = []
        callbacks = [lambda k, i=i: calls.append((i, k)) for i in range(5)]

        def broken(k: int) -> None:
            raise RuntimeError("a bug in one player")

        async def until(n: int) -> None:  # n calls in, however late the loop runs
            async with asyncio.timeout(30):
                while len(calls) < n:
                    await asyncio.sleep(0.001)

        ticker.subscribe(callbacks[0])
        ticker.subscribe(broken)  # logged; the others keep their schedule
        for c in callbacks[1:]:
            ticker.subscribe(c)
        await until(10)  # slot 0 at once, then the next one served (1 unless late)
        k = calls[5][1]
        assert k > 0 and calls[:10] == [(i, s) for s in (0, k) for i in range(5)]
        ticker.unsubscribe(callbacks[0])  # one player leaving leaves the others called
        last = calls[-1][1]
        calls.clear()
        await until(4)
        k = calls[0][1]
        assert k > last and calls[:4] == [(i, k) for i in range(1, 5)]  # in order, together
        for c in [*callbacks[1:], broken]:
            ticker.unsubscribe(c)
        assert ticker._timer is None  # nobody left: no timer

    asyncio.run(main())


def test_ticker_rejects_bad_rates() -> None:
    for rate in (0.0, -5.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="positive"):
            Ticker(rate)


# --------------------------------------------------------------------------- messages
ROLES = ("head", "hip", "left_hand", "right_hand", "left_foot", "right_foot")


def _sample(seed: int = 0, roles: tuple[str, ...] = ROLES) -> DeviceSample:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(len(roles), 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return DeviceSample.of(12345.678901234, roles, rng.uniform(-2, 2, (len(roles), 3)), q)


def test_tracker_frame_from_a_sample_round_trips_exactly() -> None:
    s = _sample(1)
    msg = tracker_frame(41, s, clock_offset=-3.25e-4)
    assert msg.seq == 41 and msg.roles == ROLES
    assert msg.t_capture == s.t_capture and msg.clock_offset == -3.25e-4
    assert msg.t_capture_server == s.t_capture - 3.25e-4
    # the poses as they travel (protocol 4): positions within half a float32 ulp,
    # quaternion components within half an int16 level
    np.testing.assert_array_equal(msg.positions, s.positions.astype(np.float32))
    np.testing.assert_allclose(msg.positions, s.positions, rtol=2**-24, atol=0)
    np.testing.assert_allclose(msg.rotations, s.rotations, rtol=0, atol=0.5 / 32767 + 1e-12)
    assert not np.array_equal(msg.rotations, s.rotations)
    back = decode(encode(msg))
    assert isinstance(back, TrackerFrame)
    assert back.seq == msg.seq and back.roles == msg.roles
    assert back.t_capture == msg.t_capture and back.clock_offset == msg.clock_offset
    np.testing.assert_array_equal(back.poses, msg.poses)  # bit for bit
    assert back.poses.dtype == np.float64 and back.poses.shape == (6, 7)


def test_calibrate_from_a_sample_round_trips_exactly() -> None:
    s = _sample(2, (*ROLES, "left_knee"))
    msg = calibrate_message(s, clock_offset=0.5)
    back = decode(encode(msg))
    assert isinstance(back, Calibrate)
    assert back.roles == s.roles and back.t_capture == s.t_capture
    np.testing.assert_array_equal(back.poses, msg.poses)
    # the sample's rows as they travel: positions as float32 (within 2 m: an ulp is
    # 1.2e-7), quaternion components within half an int16 level
    np.testing.assert_allclose(msg.positions, s.positions, rtol=0, atol=2**-23)
    np.testing.assert_allclose(msg.rotations, s.rotations, rtol=0, atol=0.5 / 32767 + 1e-12)


def test_messages_from_the_builtin_motion_source() -> None:
    src = BvhSource(builtin_motion_path())
    cal = calibrate_message(src.calibration(), 0.0)  # has every role calibration needs
    sample = src.read()
    assert sample is not None
    frame = decode(encode(tracker_frame(0, sample, 0.0)))
    assert isinstance(frame, TrackerFrame) and frame.roles == sample.roles
    np.testing.assert_array_equal(frame.positions, sample.positions.astype(np.float32))
    assert cal.roles == src.calibration().roles


def test_a_bad_sample_is_refused_by_the_message() -> None:
    s = _sample(3)
    s.positions[2, 1] = np.nan
    with pytest.raises(ValueError, match="left_hand"):
        tracker_frame(0, s, 0.0)
    with pytest.raises(ValueError, match="left_hand"):  # the player's direct encoder too
        encode_tracker_frame(0, s.roles, s.poses, s.t_capture, 0.0)


def test_direct_tracker_encoder_gives_the_model_bytes() -> None:
    for seed, roles in ((4, ROLES), (5, (*ROLES, "left_knee", "right_forearm")), (6, ROLES)):
        s = _sample(seed, roles)
        if seed == 6:  # quaternions off unit within the tolerance: both normalise alike
            s.rotations[:] *= 1.0004
        assert encode_tracker_frame(2**40 + seed, s.roles, s.poses, s.t_capture,
                                    -1.5e-3) == encode(tracker_frame(2**40 + seed, s,
                                                                     -1.5e-3))


# --------------------------------------------------------------------------- spectator
OFFSET = 100.0  # server clock - local clock


def _frame(avatar_id: int, seq: int, t_capture: float) -> AvatarFrame:
    return AvatarFrame(avatar_id=avatar_id, seq=seq, root=np.array([0.0, 1.0, 0.0]),
                       rotations=np.tile([0.0, 0.0, 0.0, 1.0], (3, 1)),
                       t_capture=t_capture, t_server_receive=t_capture + 0.001,
                       t_solved=t_capture + 0.0012, t_sent=t_capture + 0.0015)


def _info(avatar_id: int) -> AvatarInfo:
    return AvatarInfo(avatar_id=avatar_id, display_name=f"p{avatar_id}",
                      joint_names=("hips", "spine", "head"), parents=(-1, 0, 1),
                      rest_offsets=np.array([[0, 1, 0], [0, 0.2, 0], [0, 0.5, 0]], float))


def test_spectator_records_batches_on_the_server_clock() -> None:
    spec = Spectator("ws://x", "room", "viewer")
    clock = ClockEstimator()
    spec.on_batch(AvatarBatch.from_frames([_frame(1, 0, 200.0)], t_sent=200.0015), 100.002,
                  clock)
    # not synced yet: only the stages that need no local clock
    assert set(spec.stats.latency.stages) == {"capture_to_server", "solve", "server"}
    clock.add(0.0, OFFSET, OFFSET, 0.0)  # a zero-RTT exchange: offset exactly 100
    batch = decode(encode(AvatarBatch.from_frames([_frame(1, 1, 200.0), _frame(2, 7, 200.0)],
                                                 t_sent=200.0015)))
    assert isinstance(batch, AvatarBatch)
    spec.on_batch(batch, 100.003, clock)  # received at 200.003 server time
    lat = spec.stats.latency
    np.testing.assert_allclose(lat.samples("capture_to_spectator"), [0.003, 0.003],
                               atol=1e-9)
    np.testing.assert_allclose(lat.samples("network_to_spectator"), [0.0015, 0.0015],
                               atol=1e-9)
    assert lat.counts()["server"] == 3
    assert spec.stats.frames_received == 3 and spec.stats.batches_received == 2
    assert spec.stats.frames_per_avatar == {1: 2, 2: 1}
    assert frame_of(spec.latest[1]).seq == 1 and spec.latest[1][2] == 100.003
    assert frame_of(spec.latest[2]).seq == 7


def test_spectator_roster_adds_updates_and_removes() -> None:
    spec = Spectator("ws://x", "room", "viewer", max_rate_hz=30.0)
    assert spec.hello.max_rate_hz == 30.0 and spec.hello.role == "spectator"
    spec.on_roster(AvatarRoster(avatars=(_info(1), _info(2))))
    spec.on_batch(AvatarBatch.from_frames([_frame(2, 0, 1.0)], t_sent=1.0015), 0.0,
                  ClockEstimator())
    spec.on_roster(AvatarRoster(avatars=(_info(1),), removed=(2,)))
    assert sorted(spec.roster) == [1] and 2 not in spec.latest
    assert spec.stats.frames_per_avatar[2] == 1  # counts outlive the avatar


# --------------------------------------------------------------------------- connection
def _hello() -> Hello:
    return Hello(protocol_version=PROTOCOL_VERSION, role="spectator", room="r",
                 display_name="v")


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_connection_refused_is_one_clear_line() -> None:
    url = f"ws://127.0.0.1:{_closed_port()}"
    with pytest.raises(SessionError) as info:
        asyncio.run(open_session(url, _hello(), timeout=2.0))
    text = str(info.value)
    assert text.startswith(url + ": ") and "refused" in text and "\n" not in text
    assert info.value.url == url and info.value.code is None


def test_not_a_websocket_url() -> None:
    with pytest.raises(SessionError, match="not a websocket URL"):
        asyncio.run(open_session("localhost:8765", _hello()))


def test_an_invalid_hello_is_one_clear_line() -> None:
    with pytest.raises(SessionError, match=r"^ws://h:1: cannot join: hello\.room: ") as info:
        Spectator("ws://h:1", "no spaces allowed", "viewer")
    assert "\n" not in str(info.value)
    with pytest.raises(SessionError, match="max_rate_hz"):
        Spectator("ws://h:1", "room", "viewer", max_rate_hz=-1.0)
