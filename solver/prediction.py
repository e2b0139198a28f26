"""Motion prediction: carry poses forward by a known delay.

A viewer shows a pose captured some time ago; prediction shows where that pose is going.
Every predictor here is one formula over the last few samples of each element (a joint's
rotation, a root's or a device's position), batched over all of them at once:

- ``d_k = x_{-k} - x_0`` for the last K samples before the newest ``x_0`` (captured tau_k < 0
  seconds earlier); for rotations ``d_k = log(q_0^-1 q_{-k})``, a rotation vector in the
  newest sample's frame, so positions and rotations share the same linear maths;
- a polynomial through the newest sample, ``d(tau) = v tau + a tau^2 / 2``, fitted to the
  d_k by least squares weighted exp(tau / decay), gives the offset ``v h + g a h^2 / 2`` at
  horizon h (g: how much of the fitted acceleration is trusted);
- the prediction is ``x_0 + offset`` (``q_0 exp(offset)`` for rotations).

Kinds (``PredictorParams.kind``):

- ``velocity``: constant-velocity extrapolation from the last two samples (the textbook
  anchor; SteamVR's "seconds to photons" prediction of device poses works from velocity).
- ``slimevr``: SlimeVR's prediction filter: the average of the last frame-to-frame deltas
  (its buffer holds 6), carried over the horizon.
- ``posecast``: the fit above over a window, recent samples weighted most; optionally
  speed-adaptive in the spirit of the 1-euro filter (slow elements, where noise dominates,
  a long window; fast ones, where lag dominates, a short one) and with damped
  acceleration. Chosen by leave-one-clip-out (``posecast bench prediction``), the shipped
  constants use neither: on these recordings both cost accuracy and added shaking.

Pure: numpy in, numpy out. ``predict_sequence`` scores whole recordings (the eval);
``predict_latest`` carries one avatar's newest pose forward (the viewer).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from posecast.solver import rotations as R
from posecast.solver.choices import PREDICTORS

Array = NDArray[np.float64]

KINDS = PREDICTORS  # (solver.choices: the command line offers them before numpy loads)
SLIMEVR_BUFFER = 6  # frame-to-frame deltas SlimeVR averages (its PREDICT_BUFFER)
MAX_HORIZON_S = 0.25  # beyond this an extrapolated limb is a guess: hold there instead


@dataclass(frozen=True)
class PredictorParams:
    """One predictor and its constants. Windows are in seconds so that one setting serves
    recordings and players of any frame rate; speeds are where the short window takes over
    completely."""

    kind: str = "posecast"
    window_s: float = 0.12  # the samples fitted (long window: slow elements)
    decay_s: float = 0.02  # the fit weighs a sample exp(tau / decay_s): recent ones more
    accel_gain: float = 0.0  # share of the fitted acceleration used
    short_window_s: float = 0.06  # fast elements (with fast_speed / fast_turn)
    fast_speed: float = np.inf  # m/s: inf = one window for all speeds
    fast_turn: float = np.inf  # rad/s
    max_horizon_s: float = MAX_HORIZON_S

    def with_(self, **changes: object) -> PredictorParams:
        return replace(self, **changes)  # type: ignore[arg-type]


# The shipped constants: chosen by `posecast bench prediction` (leave-one-clip-out over the
# Vive recordings and the BVH clips at 50 ms); docs/performance.md has the table.
DEFAULT = PredictorParams()
BASELINES = {"velocity": PredictorParams(kind="velocity"),
             "slimevr": PredictorParams(kind="slimevr")}


def fit_weights(tau: Array, h: float, accel_gain: float,
                decay_s: float = np.inf) -> tuple[Array, Array]:
    """Weights (K,) of the least-squares fit through the newest sample: the offset at
    horizon ``h`` is sum_k w_k d_k, the velocity sum_k v_k d_k. ``tau`` (K,): the samples'
    times relative to the newest (< 0). One sample: constant velocity; two or more: a
    quadratic whose acceleration counts ``accel_gain`` times."""
    tau = np.asarray(tau, np.float64)
    if len(tau) == 1:
        v = np.array([1.0 / tau[0]])
        return h * v, v
    A = np.stack([tau, 0.5 * tau * tau], axis=1)
    sw = np.sqrt(np.exp(tau / decay_s))[:, None]  # weighted least squares
    P = np.linalg.pinv(A * sw) * sw.T  # (2, K): d -> (v, a)
    return h * P[0] + accel_gain * 0.5 * h * h * P[1], P[0]


def _slimevr_weights(tau: Array, h: float) -> tuple[Array, Array]:
    """Average of the deltas over the buffer: (x_0 - x_-K) / (K dt), velocity times h."""
    v = np.zeros(len(tau))
    v[-1] = 1.0 / tau[-1]
    return h * v, v


def _lags(kind: str, window_s: float, dt: float) -> int:
    if kind == "velocity":
        return 1
    if kind == "slimevr":
        return SLIMEVR_BUFFER
    return max(1, round(window_s / dt))


@dataclass(frozen=True)
class _Weights:
    """One predictor's weights over the lags at one horizon, shared by rotations and
    positions (computed once per call: the fits are the costly part for a few joints)."""

    long: Array  # (K,) offset at the horizon
    velocity: Array  # (K,) velocity, for the speed-adaptive blend
    short: Array | None  # (k,) offset from the short window, None when not adaptive

    @classmethod
    def of(cls, params: PredictorParams, tau: Array, h: float) -> _Weights:
        if params.kind == "velocity":
            w, v = fit_weights(tau[:1], h, 0.0)
            return cls(np.pad(w, (0, len(tau) - 1)), np.pad(v, (0, len(tau) - 1)), None)
        if params.kind == "slimevr":
            w, v = _slimevr_weights(tau, h)
            return cls(w, v, None)
        w, v = fit_weights(tau, h, params.accel_gain, params.decay_s)
        if not (np.isfinite(params.fast_speed) or np.isfinite(params.fast_turn)):
            return cls(w, v, None)
        k_short = int(np.clip(round(params.short_window_s / -tau[0]), 1, len(tau)))
        short, _ = fit_weights(tau[:k_short], h, params.accel_gain, params.decay_s)
        return cls(w, v, short)

    def offset(self, d: Array, fast: float) -> Array:
        """Offset at the horizon from deltas d (K, ..., 3), blended towards the short
        window's by speed when adaptive."""
        used = np.flatnonzero(self.long)  # the baselines weigh one lag each
        long = np.tensordot(self.long[used], d[used], axes=1)
        if self.short is None or not np.isfinite(fast):
            return np.asarray(long)
        short = np.tensordot(self.short, d[:len(self.short)], axes=1)
        speed = np.linalg.norm(np.tensordot(self.velocity, d, axes=1), axis=-1, keepdims=True)
        return np.asarray(long + np.clip(speed / fast, 0.0, 1.0) * (short - long))


def _rotation_deltas(q: Array, lags: int) -> Array:
    """(K, F, N, 3): log(q_f^-1 q_{f-k}) for k = 1..K (frames before 0 repeat frame 0)."""
    F = q.shape[0]
    inv = R.conjugate(q)
    out = np.empty((lags, *q.shape[:-1], 3))
    for k in range(1, lags + 1):
        past = q[np.maximum(np.arange(F) - k, 0)]
        out[k - 1] = R.to_rotvec(R.mul(inv, past))
    return out


def _position_deltas(p: Array, lags: int) -> Array:
    F = p.shape[0]
    out = np.empty((lags, *p.shape))
    for k in range(1, lags + 1):
        out[k - 1] = p[np.maximum(np.arange(F) - k, 0)] - p
    return out


@dataclass
class SequenceDeltas:
    """A recording's deltas, computed once and reused by every predictor and horizon
    (the bench tries many)."""

    rotations: Array  # (F, N, 4)
    positions: Array  # (F, M, 3)
    dt: float
    dq: Array  # (K, F, N, 3)
    dp: Array  # (K, F, M, 3)

    @classmethod
    def of(cls, rotations: Array, positions: Array, fps: float, lags: int) -> SequenceDeltas:
        return cls(rotations, positions, 1.0 / fps, _rotation_deltas(rotations, lags),
                   _position_deltas(positions, lags))

    def predict(self, params: PredictorParams, h: float) -> tuple[Array, Array]:
        """Every frame carried forward by ``h`` seconds from the frames up to it."""
        if h <= 0.0:
            return self.rotations, self.positions
        h = min(h, params.max_horizon_s)
        K = min(_lags(params.kind, params.window_s, self.dt), self.dq.shape[0])
        tau = -self.dt * np.arange(1, K + 1)
        w = _Weights.of(params, tau, h)
        rv = w.offset(self.dq[:K], params.fast_turn)
        dp = w.offset(self.dp[:K], params.fast_speed)
        return R.normalize(R.mul(self.rotations, R.from_rotvec(rv))), self.positions + dp


def lags_needed(params: PredictorParams, fps: float) -> int:
    return _lags(params.kind, params.window_s, 1.0 / fps)


def predict_sequence(rotations: Array, positions: Array, fps: float, h: float,
                     params: PredictorParams = DEFAULT) -> tuple[Array, Array]:
    """Rotations (F, N, 4) and positions (F, M, 3) sampled at ``fps``: each frame f
    carried forward by ``h`` seconds using frames <= f only (what a viewer has)."""
    if h <= 0.0:
        return rotations, positions
    deltas = SequenceDeltas.of(rotations, positions, fps, lags_needed(params, fps))
    return deltas.predict(params, h)


def predict_latest(times: Array, rotations: Array, positions: Array, t: float,
                   params: PredictorParams = DEFAULT) -> tuple[Array, Array]:
    """The newest of a few recent samples carried forward to instant ``t``.

    ``times`` (S,) ascending capture times, ``rotations`` (S, N, 4), ``positions`` (S, M, 3).
    Uses the samples within the predictor's window (its lags at the samples' median
    spacing); one sample, or ``t`` not after the newest: the newest as it is."""
    times = np.asarray(times, np.float64)
    h = min(t - float(times[-1]), params.max_horizon_s)
    if len(times) < 2 or h <= 0.0:
        return rotations[-1], positions[-1]
    dt = float(np.median(np.diff(times)))
    K = min(_lags(params.kind, params.window_s, dt) if dt > 0 else 1, len(times) - 1)
    tau = times[-2 - np.arange(K)] - times[-1]  # newest first: tau[0] is the latest lag
    if np.any(tau >= 0.0):
        return rotations[-1], positions[-1]
    q0, p0 = rotations[-1], positions[-1]
    w = _Weights.of(params, tau, h)
    # only the lags the weights use (the baselines' one) are worth a logarithm
    lags = np.arange(K) if w.short is not None else np.flatnonzero(w.long)
    dq = np.zeros((K, *q0.shape[:-1], 3))
    dq[lags] = R.to_rotvec(R.mul(R.conjugate(q0)[None], rotations[-2 - lags]))
    dp = positions[-2 - np.arange(K)] - p0[None]
    rv = w.offset(dq, params.fast_turn)
    off = w.offset(dp, params.fast_speed)
    return R.normalize(R.mul(q0, R.from_rotvec(rv))), p0 + off
