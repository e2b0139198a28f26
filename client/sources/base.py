"""What every pose source gives the player: device poses sampled at a known instant.

A source is anything that yields the poses of the player's tracked devices (headset,
controllers, trackers) by role: OpenVR on a real rig, a Vive recording or a BVH file
replayed in real time. The player loop paces itself at ``rate_hz`` and calls ``read``;
the capture time is taken when the pose is read, on this process's ``now()`` clock.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

# device roles, as the protocol and DESIGN.md spell them
ROLES = ("head", "hip", "left_hand", "right_hand", "left_forearm", "right_forearm",
         "left_foot", "right_foot", "left_knee", "right_knee", "chest")


def now() -> float:
    """The client's clock, seconds (monotonic; offsets to the server clock come from pings)."""
    return time.perf_counter()


@dataclass(frozen=True)
class DeviceSample:
    """Poses of the devices seen at one instant (metres, +y up; quaternions x, y, z, w),
    one row per role in the protocol's layout, position | quaternion: a player sends the
    rows as they are (joining separate arrays on every frame cost a player ~1 us)."""

    t_capture: float  # now() when the poses were read
    roles: tuple[str, ...]  # subset of ROLES, in the order of the rows
    poses: NDArray[np.float64]  # (D, 7)

    @classmethod
    def of(cls, t_capture: float, roles: tuple[str, ...], positions: NDArray[np.float64],
           rotations: NDArray[np.float64]) -> DeviceSample:
        """A sample from positions (D, 3) and rotations (D, 4) (a new array)."""
        return cls(t_capture, roles, np.concatenate(
            [np.asarray(positions, dtype=np.float64), np.asarray(rotations, dtype=np.float64)],
            axis=1))

    @property
    def positions(self) -> NDArray[np.float64]:  # (D, 3), a view
        return self.poses[:, :3]

    @property
    def rotations(self) -> NDArray[np.float64]:  # (D, 4), a view
        return self.poses[:, 3:]


class SourceError(RuntimeError):
    """A source that cannot start (no SteamVR, unreadable file): one clear line for the user."""


class PoseSource(Protocol):
    rate_hz: float  # how often the player should read

    def calibration(self) -> DeviceSample:
        """The T-pose sample to calibrate the avatar with (standing, arms sideways)."""
        ...

    def read(self) -> DeviceSample | None:
        """The poses now; None when the source has ended (a recording not looped)."""
        ...

    def close(self) -> None:
        ...


class OffsetSource:
    """Another source's poses moved sideways by ``offset`` (x, z metres) before they are
    sent, so that players replaying one clip stand apart instead of inside each other.
    Rotations are unchanged. Each sample gets new rows: a source may hand out its own."""

    def __init__(self, source: PoseSource, offset: tuple[float, float]) -> None:
        self.source = source
        self.offset = offset
        self.rate_hz = source.rate_hz
        self._shift = np.array([offset[0], 0.0, offset[1], 0.0, 0.0, 0.0, 0.0])

    def _moved(self, sample: DeviceSample) -> DeviceSample:
        return DeviceSample(sample.t_capture, sample.roles, sample.poses + self._shift)

    def calibration(self) -> DeviceSample:
        return self._moved(self.source.calibration())

    def read(self) -> DeviceSample | None:
        sample = self.source.read()
        return None if sample is None else self._moved(sample)

    def close(self) -> None:
        self.source.close()
