"""Simulated tracking losses (``--dropouts RATE[,max=S][,seed=N]``): each driving device
but the head is lost at random, RATE times a minute on average, each time for 0.05 s to
S s (log-uniform), as a tracker hidden from the base stations is. The same seed gives the
same losses, and each device's losses do not depend on which other devices there are."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from posecast.solver.tracking.devices import DEVICES

MIN_LOSS_S = 0.05
DEFAULT_MAX_S = 2.0


@dataclass(frozen=True)
class DropoutSpec:
    rate_per_min: float
    max_s: float = DEFAULT_MAX_S
    seed: int = 0

    def __str__(self) -> str:
        return f"{self.rate_per_min:g}/min, 0.05-{self.max_s:g} s, seed {self.seed}"


def parse_dropouts(spec: str) -> DropoutSpec:
    """``RATE[,max=S][,seed=N]`` -> DropoutSpec; ValueError (one line) otherwise."""
    usage = f"--dropouts {spec!r}: expected RATE[,max=S][,seed=N], e.g. 6,max=2,seed=7"
    parts = [p.strip() for p in spec.split(",")]
    try:
        rate = float(parts[0])
        extra = dict(p.split("=", 1) for p in parts[1:])
        max_s = float(extra.pop("max", DEFAULT_MAX_S))
        seed = int(extra.pop("seed", 0))
    except ValueError:
        raise ValueError(usage) from None
    if extra:
        raise ValueError(f"{usage}; unknown: {', '.join(extra)}")
    if not (math.isfinite(rate) and 0.0 <= rate <= 600.0):
        raise ValueError(f"{usage}; the rate is losses a minute, 0 to 600")
    if not (math.isfinite(max_s) and MIN_LOSS_S <= max_s <= 600.0):
        raise ValueError(f"{usage}; max is seconds, {MIN_LOSS_S} to 600")
    if seed < 0:
        raise ValueError(f"{usage}; the seed is a whole number >= 0")
    return DropoutSpec(rate, max_s, seed)


class DropoutSchedule:
    """When each device is lost, generated as time goes on (for a live player, or a
    recording of any length)."""

    def __init__(self, spec: DropoutSpec) -> None:
        self.spec = spec
        self._rng = {d: np.random.default_rng([spec.seed, i]) for i, d in enumerate(DEVICES)}
        self._next = {d: self._gap(d) for d in DEVICES}  # next loss starts (s)
        self._until = dict.fromkeys(DEVICES, -1.0)  # the current loss ends (s)

    def _gap(self, device: str) -> float:
        rate = self.spec.rate_per_min / 60.0
        return math.inf if rate <= 0.0 else float(self._rng[device].exponential(1.0 / rate))

    def lost(self, device: str, t: float) -> bool:
        """Is the device lost at time t (seconds from the start; t never decreases)?
        The head is never lost."""
        if device == "head":
            return False
        while t >= self._next[device]:  # losses started by now
            start = self._next[device]
            lo, hi = math.log(MIN_LOSS_S), math.log(self.spec.max_s)
            length = math.exp(self._rng[device].uniform(lo, hi))
            self._until[device] = max(self._until[device], start + length)
            self._next[device] = start + length + self._gap(device)
        return t < self._until[device]


def dropout_mask(spec: DropoutSpec, devices: tuple[str, ...], frames: int,
                 fps: float) -> NDArray[np.bool_]:
    """(frames, len(devices)): True where the device is lost in that frame."""
    schedule = DropoutSchedule(spec)
    out = np.zeros((frames, len(devices)), dtype=bool)
    for f in range(frames):
        t = f / fps
        for d, name in enumerate(devices):
            out[f, d] = schedule.lost(name, t)
    return out
