"""Latency samples per pipeline stage, their percentiles, and a table for the terminal.

A spectator records the stages of every avatar frame it receives
(``AvatarFrame.latencies``: capture_to_server, solve, server, network_to_spectator,
capture_to_spectator; a viewer adds the presented stages). Samples are seconds on the
server clock; ``summary`` reports milliseconds, in the shape of the ``latency_ms`` key
of ``posecast demo --json``. Recorders of several spectators merge into one, so the
percentiles are over all samples (not an average of per-spectator percentiles, which
would be meaningless for tails).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray

from posecast.protocol.batch import stage_latencies

# the order stages are listed in: along the way a pose travels
STAGE_ORDER = ("capture_to_server", "solve", "server", "relay", "network_to_spectator",
               "capture_to_spectator", "capture_to_decoded", "receive_to_render",
               "capture_to_render",
               "receive_to_presented", "capture_to_presented")
PERCENTILES = (("p50", 50.0), ("p95", 95.0), ("p99", 99.0))

Summary = dict[str, dict[str, float]]


class _Samples:
    """A growing float64 buffer: amortised O(1) append without a Python list of floats."""

    __slots__ = ("data", "n")

    def __init__(self, capacity: int) -> None:
        self.data = np.empty(max(capacity, 1), dtype=np.float64)
        self.n = 0

    def _reserve(self, extra: int) -> None:
        need = self.n + extra
        if need > self.data.shape[0]:
            grown = np.empty(max(need, 2 * self.data.shape[0]), dtype=np.float64)
            grown[:self.n] = self.data[:self.n]
            self.data = grown

    def append(self, value: float) -> None:
        if self.n == self.data.shape[0]:
            self._reserve(1)
        self.data[self.n] = value
        self.n += 1

    def fill(self, count: int, value: float) -> None:
        self._reserve(count)
        self.data[self.n:self.n + count] = value
        self.n += count

    def extend(self, values: NDArray[np.float64]) -> None:
        self._reserve(values.shape[0])
        self.data[self.n:self.n + values.shape[0]] = values
        self.n += values.shape[0]

    def view(self) -> NDArray[np.float64]:
        return self.data[:self.n]


class LatencyRecorder:
    """Latency samples (seconds) per stage name.

    ``add`` takes the dict ``AvatarFrame.latencies`` or ``AvatarBatch.latencies``
    returns; ``add_values`` a whole array for one stage; ``add_batch`` a received
    batch's times. ``capacity`` is the initial size of each stage's buffer (90 Hz x 16
    avatars x 20 s is ~29k samples; buffers double as needed).
    """

    def __init__(self, capacity: int = 4096) -> None:
        self.capacity = capacity
        self._buffers: dict[str, _Samples] = {}
        # add_batch's columns: t_capture, t_server_receive, t_solved, t_sent, t_received,
        # t_decoded (NaN: not known), a row per avatar-frame
        self._times = np.empty((6, max(capacity, 1)))
        self._rows = 0

    def add_batch(self, t_capture: NDArray[np.float64], t_server_receive: NDArray[np.float64],
                  t_solved: NDArray[np.float64], t_sent: float,
                  t_received: float | None = None, t_decoded: float | None = None) -> None:
        """A received batch's times (columns of one value per avatar; seconds on the
        server clock), kept as they are: its stages are computed when read, for all
        batches at once. Computing five stages per batch as it arrived cost a spectator
        as much as decoding the batch, on the path of every spectator after it in the
        same process; six slices of one table here."""
        start, end = self._rows, self._rows + t_capture.shape[0]
        times = self._times
        if end > times.shape[1]:
            grown = np.empty((6, max(end, 2 * times.shape[1])))
            grown[:, :start] = times[:, :start]
            times = self._times = grown
        times[0, start:end] = t_capture
        times[1, start:end] = t_server_receive
        times[2, start:end] = t_solved
        times[3, start:end] = t_sent
        times[4, start:end] = math.nan if t_received is None else t_received
        times[5, start:end] = math.nan if t_decoded is None else t_decoded
        self._rows = end

    def _fold(self) -> None:
        """Turn the batch times into stage samples (rows without a receive time get no
        receive-side stages)."""
        t_capture, t_server_receive, t_solved, t_sent, t_received, t_decoded = (
            self._times[:, :self._rows])
        synced = ~np.isnan(t_received)
        for rows, received in ((synced, t_received), (~synced, None)):
            if rows.any():
                self.add(stage_latencies(t_capture[rows], t_server_receive[rows],
                                         t_solved[rows], t_sent[rows],
                                         None if received is None else received[rows]))
        rows = ~np.isnan(t_decoded)
        if rows.any():
            self._buffer("capture_to_decoded").extend(stage_latencies(
                t_capture[rows], t_server_receive[rows], t_solved[rows], t_sent[rows],
                t_decoded=t_decoded[rows])["capture_to_decoded"])
        self._rows = 0

    @property
    def _stages(self) -> dict[str, _Samples]:
        """Every stage's samples, the batches' times included."""
        if self._rows:
            self._fold()
        return self._buffers

    def _buffer(self, stage: str) -> _Samples:
        buf = self._buffers.get(stage)
        if buf is None:
            buf = self._buffers[stage] = _Samples(self.capacity)
        return buf

    def add(self, latencies: Mapping[str, float | NDArray[np.float64]]) -> None:
        """Stage durations, seconds: one frame's (floats, ``AvatarFrame.latencies``) or
        a batch's (an array per stage, ``AvatarBatch.latencies``)."""
        for stage, seconds in latencies.items():
            if isinstance(seconds, np.ndarray):
                self._buffer(stage).extend(seconds)
            else:
                self._buffer(stage).append(seconds)

    def add_values(self, stage: str, seconds: ArrayLike) -> None:
        """Many samples of one stage at once, seconds."""
        values = np.asarray(seconds, dtype=np.float64).reshape(-1)
        self._buffer(stage).extend(values)

    def extend(self, other: LatencyRecorder) -> None:
        """Add every sample of ``other`` to this recorder."""
        for stage, buf in other._stages.items():
            self._buffer(stage).extend(buf.view())

    @classmethod
    def merged(cls, recorders: Iterable[LatencyRecorder]) -> LatencyRecorder:
        """One recorder holding the samples of all of them (e.g. every spectator's)."""
        out = cls()
        for r in recorders:
            out.extend(r)
        return out

    @property
    def stages(self) -> list[str]:
        """Stage names that have samples, in pipeline order (unknown ones last, sorted)."""
        names = [s for s, buf in self._stages.items() if buf.n]
        return sorted(names, key=_stage_key)

    def samples(self, stage: str) -> NDArray[np.float64]:
        """The samples of one stage, seconds (a view: copy it to keep it)."""
        buf = self._stages.get(stage)
        return buf.view() if buf is not None else np.empty(0)

    def counts(self) -> dict[str, int]:
        """Number of samples per stage."""
        return {s: self._stages[s].n for s in self.stages}

    def __len__(self) -> int:
        """Samples of the stage with the most (frames recorded, when every frame has it)."""
        return max((buf.n for buf in self._stages.values()), default=0)

    def summary(self) -> Summary:
        """``{stage: {"p50", "p95", "p99"}}`` in milliseconds, for stages with samples."""
        out: Summary = {}
        qs = [q for _, q in PERCENTILES]
        for stage in self.stages:
            values = np.percentile(self._stages[stage].view(), qs) * 1e3
            out[stage] = {name: float(v) for (name, _), v in zip(PERCENTILES, values,
                                                                 strict=True)}
        return out


def _stage_key(stage: str) -> tuple[int, str]:
    return (STAGE_ORDER.index(stage) if stage in STAGE_ORDER else len(STAGE_ORDER), stage)


def format_latency_table(summary: Mapping[str, Mapping[str, float]],
                         counts: Mapping[str, int] | None = None,
                         decimals: int = 3) -> str:
    """A plain-text table of a ``summary``: one row per stage, ms, columns aligned.

    ``counts`` (stage -> samples, as ``LatencyRecorder.counts``) adds a samples column.
    A missing value prints as ``-``. Example::

        stage                  samples   p50 ms   p95 ms   p99 ms
        capture_to_server        28800    0.412    0.801    1.204
    """
    stages = sorted(summary, key=_stage_key)
    names = [name for name, _ in PERCENTILES]
    header = ["stage"] + (["samples"] if counts is not None else []) + \
        [f"{n} ms" for n in names]
    rows = []
    for stage in stages:
        row = [stage]
        if counts is not None:
            row.append(str(counts.get(stage, 0)))
        row += [_ms(summary[stage].get(n), decimals) for n in names]
        rows.append(row)
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    # stage names left-aligned, numbers right-aligned so the decimal points line up
    lines = ["  ".join(cell.ljust(w) if i == 0 else cell.rjust(w)
                       for i, (cell, w) in enumerate(zip(r, widths, strict=True)))
             for r in [header, *rows]]
    return "\n".join(line.rstrip() for line in lines)


def _ms(value: float | None, decimals: int) -> str:
    if value is None or not math.isfinite(value):
        return "-"
    return f"{value:.{decimals}f}"
