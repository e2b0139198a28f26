"""protocol.clock: NTP offset math, and an estimator that trusts low-RTT samples."""

from __future__ import annotations

import math

import numpy as np
import pytest

from posecast.protocol import ClockEstimator, Pong, clock_sample

TRUE_OFFSET = 1234.567891  # server clock - client clock, seconds


def exchange(t0: float, d_up: float, hold: float, d_down: float,
             offset: float = TRUE_OFFSET) -> tuple[float, float, float, float]:
    """(t0, t1, t2, t3) of one Ping/Pong with the given one-way delays and server hold."""
    t1 = t0 + offset + d_up
    t2 = t1 + hold
    t3 = t2 - offset + d_down
    return t0, t1, t2, t3


def test_symmetric_delays_give_the_exact_offset() -> None:
    sample = clock_sample(*exchange(100.0, 0.002, 0.0005, 0.002))
    assert sample.offset == pytest.approx(TRUE_OFFSET, abs=1e-9)
    assert sample.rtt == pytest.approx(0.004, abs=1e-9)  # the server's hold is not RTT
    assert sample.t_local == pytest.approx(100.0045, abs=1e-9)


def test_asymmetric_delays_err_by_half_the_asymmetry() -> None:
    sample = clock_sample(*exchange(100.0, 0.010, 0.0, 0.002))
    assert sample.offset - TRUE_OFFSET == pytest.approx((0.010 - 0.002) / 2, abs=1e-9)
    assert abs(sample.offset - TRUE_OFFSET) <= sample.rtt / 2


def test_non_finite_times_are_refused() -> None:
    with pytest.raises(ValueError, match="finite"):
        clock_sample(0.0, math.nan, 1.0, 2.0)


def simulate(estimator: ClockEstimator, rng: np.random.Generator, n: int,
             offset: float = TRUE_OFFSET, start: float = 0.0) -> list[float]:
    """Pings every 0.5 s; each way 0.2 ms plus exponential jitter (mean 3 ms), independent.

    Returns the offset of each raw sample, for comparison with the estimator.
    """
    raw = []
    for i in range(n):
        t = exchange(start + 0.5 * i, 2e-4 + rng.exponential(3e-3), 1e-4,
                     2e-4 + rng.exponential(3e-3), offset)
        assert estimator.add(*t)
        raw.append(clock_sample(*t).offset)
    return raw


def test_estimator_converges_under_jitter() -> None:
    errors, naive = [], []
    for seed in range(40):
        rng = np.random.default_rng(seed)
        est = ClockEstimator()
        raw = simulate(est, rng, 60)
        error = abs(est.offset - TRUE_OFFSET)
        # guaranteed: each of the 3 best samples errs by at most its rtt / 2
        assert error <= sorted(s.rtt for s in est.samples)[2] / 2
        errors.append(error)
        naive.append(abs(raw[-1] - TRUE_OFFSET))  # trusting whatever sample came last
    # with 6 ms mean RTT, a quarter of a millisecond on average (measured: 0.25 ms) ...
    assert np.mean(errors) < 4e-4
    # ... several times better than the latest sample (measured: 5.7 x)
    assert np.mean(errors) * 3 < np.mean(naive)


def test_estimator_error_scales_with_jitter() -> None:
    for jitter, limit in ((3e-3, 4e-4), (3e-4, 4e-5), (3e-5, 4e-6)):
        errors = []
        for seed in range(20):
            rng = np.random.default_rng(seed)
            est = ClockEstimator()
            for i in range(60):
                est.add(*exchange(0.5 * i, rng.exponential(jitter), 0.0,
                                  rng.exponential(jitter)))
            errors.append(abs(est.offset - TRUE_OFFSET))
        assert np.mean(errors) < limit, jitter


def test_error_shrinks_as_samples_accumulate() -> None:
    early, late = [], []
    for seed in range(30):
        rng = np.random.default_rng(100 + seed)
        est = ClockEstimator()
        simulate(est, rng, 3)
        early.append(abs(est.offset - TRUE_OFFSET))
        simulate(est, rng, 17, start=1.5)
        late.append(abs(est.offset - TRUE_OFFSET))
    assert np.mean(late) < 0.5 * np.mean(early)


def test_prefers_low_rtt_samples() -> None:
    est = ClockEstimator(window=32, use_best=3)
    # 20 slow exchanges whose way up is 20 ms longer (offsets biased by +10 ms), and,
    # in between, 3 fast symmetric ones
    fast = (5, 11, 17)
    for i in range(23):
        delays = (0.0005, 0.0, 0.0005) if i in fast else (0.025, 0.0, 0.005)
        est.add(*exchange(0.3 * i, *delays))
    assert est.offset == pytest.approx(TRUE_OFFSET, abs=1e-9)
    assert est.rtt == pytest.approx(0.001, abs=1e-9)
    assert est.error_bound == pytest.approx(0.0005, abs=1e-9)
    # the mean of the window would be 20 x 10 ms / 23 off
    mean_all = np.mean([s.offset for s in est.samples])
    assert len(est) == 23
    assert mean_all - TRUE_OFFSET == pytest.approx(20 * 0.010 / 23, abs=1e-9)


def test_median_of_the_best_resists_one_lopsided_fast_sample() -> None:
    est = ClockEstimator(use_best=3)
    est.add(*exchange(0.0, 0.0010, 0.0, 0.0010))
    est.add(*exchange(1.0, 0.0011, 0.0, 0.0011))
    est.add(*exchange(2.0, 0.0019, 0.0, 0.0000))  # the fastest, but all of it one way
    assert est.rtt == pytest.approx(0.0019, abs=1e-12)
    assert est.offset == pytest.approx(TRUE_OFFSET, abs=1e-9)


def test_stalled_exchanges_cannot_outvote_one_that_bounds_the_offset_tighter() -> None:
    """A peer that read its first Pongs 240 ms late (a loaded machine) has two samples
    130 ms off; one exchange of a 60 ms round trip then bounds the offset within 30 ms,
    and the estimate moves inside that bound at once, not after the stalled samples
    leave the best three."""
    est = ClockEstimator(use_best=3)
    for t0 in (0.0, 0.02):
        est.add(*exchange(t0, 0.02, 0.0, 0.28))  # a 300 ms round trip, 260 ms of it down
    assert est.offset == pytest.approx(TRUE_OFFSET - 0.13, abs=1e-9)  # all it knows
    est.add(*exchange(1.0, 0.03, 0.0, 0.03))
    # every sample allows -30 to +20 ms (the stalled ones up to +20); their median,
    # -130 ms, lies outside: the estimate is the middle of what they allow
    assert est.offset == pytest.approx(TRUE_OFFSET - 0.005, abs=1e-9)


def test_old_samples_age_out_so_the_estimate_follows_a_clock_step() -> None:
    est = ClockEstimator(window=64, use_best=3, max_age=10.0)
    rng = np.random.default_rng(5)
    simulate(est, rng, 20)  # 0 .. 9.5 s
    assert est.offset == pytest.approx(TRUE_OFFSET, abs=1.5e-3)
    # the server clock is stepped by +50 ms; the new samples are slower than the old best
    simulate(est, rng, 30, offset=TRUE_OFFSET + 0.05, start=10.0)  # 10 .. 24.5 s
    assert est.offset == pytest.approx(TRUE_OFFSET + 0.05, abs=1.5e-3)
    # only the samples of the last 10 s remain: those sent at 14.5 (or 15) .. 24.5 s
    times = [s.t_local for s in est.samples]
    assert max(times) - min(times) <= 10.0
    assert min(times) > 14.5 and len(est) in (20, 21)


def test_negative_rtt_is_ignored() -> None:
    est = ClockEstimator()
    t0, t1, t2, t3 = exchange(0.0, 0.001, 0.0, 0.001)
    assert not est.add(t0, t1, t2 + 1.0, t3)  # a server hold longer than the round trip
    assert not est.synced and len(est) == 0
    assert est.offset == 0.0 and est.rtt == math.inf


def test_conversions_and_pong() -> None:
    est = ClockEstimator()
    assert est.to_server(5.0) == 5.0  # unsynced: identity
    t0, t1, t2, t3 = exchange(10.0, 0.001, 0.0002, 0.001)
    assert est.add_pong(Pong(t0=t0, t1=t1, t2=t2), t3)
    assert est.synced
    assert est.to_server(20.0) == pytest.approx(20.0 + TRUE_OFFSET, abs=1e-9)
    assert est.to_local(est.to_server(20.0)) == pytest.approx(20.0, abs=1e-9)
    est.reset()
    assert not est.synced and est.offset == 0.0


def test_bad_parameters() -> None:
    with pytest.raises(ValueError, match="use_best"):
        ClockEstimator(window=2, use_best=3)
